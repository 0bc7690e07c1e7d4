"""DesignEnv against the spec's action -> bundle rule (worked by hand and by a literal re-implementation), the
episode contract, checkpoint resume, bad input, and the paper's untrained-policy reference numbers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freeform.body import largest_component
from freeform.envs import DesignEnv, EnvConfig, Task, VecEnv, VolumeTask


def act(n: int, xyz, weights) -> torch.Tensor:
    """Actions ``[n, 3 + k]`` all equal to ``[*xyz, *weights]``."""
    return torch.tensor([[*xyz, *weights]], dtype=torch.float32).repeat(n, 1)


def covered(grid: torch.Tensor) -> list[list[int]]:
    """Sorted per-axis index sets of the non-empty cells of one grid."""
    idx = (grid != 0).nonzero()
    return [sorted(set(idx[:, d].tolist())) for d in range(3)]


def literal_reference(actions: np.ndarray, rho: int, k: int, b: int, mirror_y: bool = False) -> np.ndarray:
    """The spec's rule read literally, in float64 and the centred frame: voxel centres are the integers
    -ρ/2 … ρ/2-1, the bundle centre is p = ρ f(a) - ρ/2, a voxel is covered iff p - b/2 <= c < p + b/2."""
    n, steps, _ = actions.shape
    grids = np.zeros((n, rho, rho, rho), np.uint8)
    centres = np.arange(rho) - rho // 2
    for t in range(steps):
        f = 0.5 + np.clip(actions[:, t].astype(np.float64), -2, 2) / 4
        p = rho * f[:, :3] - rho / 2
        for i in range(n):
            masks = [(p[i, d] - b / 2 <= centres) & (centres < p[i, d] + b / 2) for d in range(3)]
            cube = masks[0][:, None, None] & masks[1][None, :, None] & masks[2][None, None, :]
            if mirror_y:  # the bundle and its reflection in the plane between the two middle y-layers
                cube = cube | cube[:, ::-1, :]
            weights = f[i, 3:]
            grids[i][cube] = int(np.flatnonzero(weights == weights.max())[0])
    return grids


# ---------------------------------------------------------------------------------------- action -> bundle
@pytest.mark.parametrize(
    ("a", "cells"),
    [
        (0.0, [9, 10]),  # centre: ρf = 10
        (1.0, [14, 15]),  # ρf = 15 exactly
        (-1.0, [4, 5]),  # ρf = 5 exactly
        (0.1, [10, 11]),  # ρf = 10.5 -> ceil 11
        (-2.0, [0]),  # ρf = 0: cells -1 (dropped) and 0
        (-7.5, [0]),  # clipped to -2
        (2.0, [19]),  # ρf = 20: cells 19 and 20 (dropped)
        (1e9, [19]),
        (1.9, [19]),  # ρf = 19.5 -> ceil 20: {19, 20} ∩ G
        (-1.9, [0, 1]),  # ρf = 0.5 -> ceil 1 -> {0, 1}
    ],
)
def test_bundle_position_by_hand(a, cells):
    env = DesignEnv(1, materials=2)
    env.reset()
    obs, *_ = env.step(act(1, (a, a, a), (0.0, 1.0)))
    assert covered(obs[0]) == [cells, cells, cells]
    assert int((obs != 0).sum()) == len(cells) ** 3


def test_bundle_is_cut_at_the_border_not_shifted():
    env = DesignEnv(1, materials=2)
    env.reset()
    obs, *_ = env.step(act(1, (-2.0, 0.0, 2.0), (0.0, 1.0)))
    assert covered(obs[0]) == [[0], [9, 10], [19]]
    assert int(obs.sum()) == 2


@pytest.mark.parametrize(
    ("rho", "k", "b"), [(20, 4, 2), (20, 2, 2), (10, 3, 4), (8, 4, 6), (6, 2, 6), (2, 2, 2)]
)
def test_placement_matches_literal_spec(rho, k, b):
    rng = np.random.default_rng(rho * 100 + k * 10 + b)
    n, steps = 16, 12
    actions = (rng.standard_normal((n, steps, 3 + k)) * 1.5).astype(np.float32)
    env = DesignEnv(n, EnvConfig(resolution=rho, steps=steps, bundle_size=b), materials=k, compute_metrics=False)
    env.reset()
    for t in range(steps):
        obs, _, done, info = env.step(torch.from_numpy(actions[:, t]))
    assert done.all()
    np.testing.assert_array_equal(info["final_grids"].numpy(), literal_reference(actions, rho, k, b))


@pytest.mark.parametrize(("rho", "k", "b"), [(8, 4, 2), (20, 4, 2), (6, 3, 2)])
def test_mirrored_designs_are_the_literal_rule_with_each_bundle_reflected_in_y(rho, k, b):
    """``mirror_y``: every step writes the bundle and its y-reflection (later bundles overwrite both), so the final
    grids are left-right symmetric and equal the literal rule applied to cube ∪ reflected cube."""
    rng = np.random.default_rng(7 + rho)
    n, steps = 16, 12
    actions = (rng.standard_normal((n, steps, 3 + k)) * 1.5).astype(np.float32)
    env = DesignEnv(n, EnvConfig(resolution=rho, steps=steps, bundle_size=b, mirror_y=True),
                    materials=k, compute_metrics=False)
    env.reset()
    for t in range(steps):
        _, _, done, info = env.step(torch.from_numpy(actions[:, t]))
    grids = info["final_grids"]
    assert done.all() and torch.equal(grids, grids.flip(2))
    np.testing.assert_array_equal(grids.numpy(), literal_reference(actions, rho, k, b, mirror_y=True))
    assert not np.array_equal(grids.numpy(), literal_reference(actions, rho, k, b))  # the reflection mattered
    assert env.state_dict()["config"]["mirror_y"] is True
    with pytest.raises(ValueError, match="does not match"):  # a mirrored state does not load into a plain env
        DesignEnv(n, EnvConfig(resolution=rho, steps=steps, bundle_size=b),
                  materials=k).load_state_dict(env.state_dict())
    with pytest.raises(ValueError, match="mirror_y must be true or false"):
        DesignEnv(n, EnvConfig(resolution=rho, mirror_y="yes"), materials=k)


def test_material_argmax_and_ties_to_lowest_index():
    env = DesignEnv(5, materials=4)
    env.reset()
    weights = torch.tensor(
        [
            [0.0, 0.5, 0.2, 0.1],  # plain argmax -> 1
            [-1.0, 3.0, 5.0, 0.0],  # 3 and 5 both clip to 2 -> tie -> 1
            [0.0, 0.0, 0.0, 0.0],  # all equal -> 0 (removal)
            [-3.0, -2.5, -9.0, 0.3],  # -> 3
            [2.0, 2.0, 7.0, 1.0],  # saturated tie with material 0 -> 0
        ]
    )
    actions = torch.cat([torch.zeros(5, 3), weights], dim=1)
    obs, *_ = env.step(actions)
    assert obs[:, 9, 9, 9].tolist() == [1, 1, 0, 3, 0]


def test_overwrite_and_removal_latest_action_wins():
    env = DesignEnv(1, EnvConfig(steps=10), materials=4)
    env.reset()
    obs, *_ = env.step(act(1, (0.0, 0.0, 0.0), (0, 0, 1, 0)))  # material 2 on {9,10}³
    assert int((obs == 2).sum()) == 8
    obs, *_ = env.step(act(1, (0.1, 0.0, 0.0), (0, 0, 0, 1)))  # material 3 on x {10,11}: overlaps half
    assert int((obs == 2).sum()) == 4 and int((obs == 3).sum()) == 8
    assert obs[0, 10, 9, 9] == 3 and obs[0, 9, 9, 9] == 2
    obs, *_ = env.step(act(1, (0.0, 0.0, 0.0), (1, 0, 0, 0)))  # material 0 removes {9,10}³
    assert int((obs == 2).sum()) == 0 and int((obs == 3).sum()) == 4
    assert int((obs[0, 9:11, 9:11, 9:11] != 0).sum()) == 0


def test_grids_step_independently():
    env = DesignEnv(3, materials=2)
    env.reset()
    actions = torch.tensor([[-1.0, -1.0, -1.0, 0, 1], [1.0, 1.0, 1.0, 0, 1], [0.0, 0.0, 0.0, 1, 0]])
    obs, *_ = env.step(actions)
    assert covered(obs[0]) == [[4, 5]] * 3 and covered(obs[1]) == [[14, 15]] * 3
    assert int(obs[2].sum()) == 0


# ------------------------------------------------------------------------------------------- episode contract
def test_protocol_and_shapes():
    env = DesignEnv(4, EnvConfig(resolution=10), materials=4)
    assert isinstance(env, VecEnv)
    assert callable(VolumeTask().reward) and Task.reward  # Task is a plain Protocol: reward(final_grids)
    assert env.observation_shape == (10, 10, 10) and env.action_dim == 7 and env.device == torch.device("cpu")
    obs = env.reset(seed=3)
    assert obs.dtype == torch.uint8 and obs.shape == (4, 10, 10, 10) and int(obs.sum()) == 0


def test_episode_rewards_done_reset_and_info():
    n, steps = 6, 5
    env = DesignEnv(n, EnvConfig(resolution=10, steps=steps), materials=3)
    g = torch.Generator().manual_seed(0)
    obs = env.reset()
    kept = []
    for t in range(steps):
        assert env.t == t
        actions = torch.randn(n, 6, generator=g)
        obs, reward, done, info = env.step(actions)
        kept.append(obs)
        assert reward.dtype == torch.float32 and reward.shape == (n,)
        assert done.dtype == torch.bool and done.shape == (n,)
        if t < steps - 1:
            assert not done.any() and (reward == 0).all() and info == {}
    assert done.all() and env.t == 0
    assert int(obs.sum()) == 0  # the next episode's empty grids
    final = info["final_grids"]
    assert final.dtype == torch.uint8 and final.shape == (n, 10, 10, 10)
    assert torch.equal(final, env.place_bundles(kept[-2], actions))  # the grid after the last action
    assert torch.equal(info["bodies"], largest_component(final))
    volume = (info["bodies"] != 0).sum(dim=(1, 2, 3)).float()
    assert torch.equal(reward, volume)
    assert torch.equal(info["metrics"]["volume"], volume)
    # Returned observations are never written to afterwards.
    assert int(kept[-1].sum()) == 0 and int(kept[0].sum()) > 0
    # The next episode starts from scratch.
    obs, reward, done, info = env.step(torch.randn(n, 6, generator=g))
    assert int((obs != 0).sum()) <= 8 * n and not done.any()


def test_without_metrics_and_custom_task():
    class Counting:
        def __init__(self):
            self.calls = 0

        def reward(self, final_grids: torch.Tensor) -> torch.Tensor:
            self.calls += 1
            return (final_grids != 0).sum(dim=(1, 2, 3)).float()

    task = Counting()
    env = DesignEnv(2, EnvConfig(resolution=6, steps=2), materials=2, task=task, compute_metrics=False)
    env.reset()
    env.step(act(2, (0, 0, 0), (0, 1)))
    _, reward, done, info = env.step(act(2, (-2, -2, -2), (0, 1)))
    assert task.calls == 1 and reward.tolist() == [9.0, 9.0]
    assert "metrics" not in info and set(info) == {"final_grids", "bodies"}


def test_task_returning_the_wrong_shape_raises():
    class Scalar:
        def reward(self, final_grids: torch.Tensor) -> torch.Tensor:
            return torch.tensor(1.0)

    env = DesignEnv(2, EnvConfig(resolution=4, steps=1), materials=2, task=Scalar())
    env.reset()
    with pytest.raises(ValueError, match="task.reward"):
        env.step(torch.zeros(2, 5))


def test_results_do_not_depend_on_batch_size():
    g = torch.Generator().manual_seed(1)
    actions = torch.randn(20, 7, 6, generator=g)
    big = DesignEnv(7, EnvConfig(resolution=12, steps=20), materials=3)
    big.reset()
    for t in range(20):
        _, big_reward, _, big_info = big.step(actions[t])
    for i in (0, 3, 6):
        one = DesignEnv(1, EnvConfig(resolution=12, steps=20), materials=3)
        one.reset()
        for t in range(20):
            _, reward, _, info = one.step(actions[t, i : i + 1])
        assert torch.equal(info["final_grids"][0], big_info["final_grids"][i])
        assert reward.item() == big_reward[i].item()
        for name, value in info["metrics"].items():
            assert value.item() == big_info["metrics"][name][i].item()


def test_state_dict_resumes_mid_episode_bit_for_bit():
    g = torch.Generator().manual_seed(2)
    actions = torch.randn(10, 4, 7, generator=g)
    env = DesignEnv(4, EnvConfig(resolution=10, steps=10), materials=4, seed=5)
    env.reset()
    for t in range(6):
        env.step(actions[t])
    state = env.state_dict()
    rest = [env.step(actions[t]) for t in range(6, 10)]
    resumed = DesignEnv(4, EnvConfig(resolution=10, steps=10), materials=4)
    resumed.load_state_dict(state)
    assert resumed.t == 6 and resumed.seed == 5
    for t, (obs, reward, done, info) in zip(range(6, 10), rest, strict=True):
        obs2, reward2, done2, info2 = resumed.step(actions[t])
        assert torch.equal(obs, obs2) and torch.equal(reward, reward2) and torch.equal(done, done2)
        assert info.keys() == info2.keys()
        for key in ("final_grids", "bodies"):
            if key in info:
                assert torch.equal(info[key], info2[key])
    # The state is a copy: stepping does not change it.
    assert int(state["t"]) == 6
    with pytest.raises(ValueError, match="config"):
        DesignEnv(4, EnvConfig(resolution=12, steps=10), materials=4).load_state_dict(state)


# ---------------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"resolution": 7}, "resolution"),
        ({"resolution": 0}, "resolution"),
        ({"resolution": -4}, "resolution"),
        ({"resolution": 20.0}, "resolution"),
        ({"bundle_size": 3}, "bundle_size"),
        ({"bundle_size": 0}, "bundle_size"),
        ({"bundle_size": 22}, "bundle_size"),
        ({"materials": 1}, "materials"),
        ({"steps": 0}, "steps"),
        ({"num_envs": 0}, "num_envs"),
    ],
)
def test_bad_config_raises(kwargs, match):
    args = {"num_envs": 2, **kwargs}
    env_args = {k: args.pop(k) for k in ("num_envs", "materials") if k in args}
    with pytest.raises(ValueError, match=match):
        DesignEnv(design=EnvConfig(**args), **env_args)


def test_bad_actions_raise():
    env = DesignEnv(2, materials=4)
    env.reset()
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(2, 6))
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(3, 7))
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.tensor([[0.0] * 7, [float("nan")] + [0.0] * 6]))
    with pytest.raises(ValueError, match="floating"):
        env.step(torch.zeros(2, 7, dtype=torch.int64))
    assert env.t == 0  # nothing was applied
    env.step(torch.full((2, 7), float("inf")))  # infinities clip like any large value


# ------------------------------------------------------------------------------------------ paper reference
def untrained_bodies(materials: int, episodes: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Volume and non-empty count of `episodes` designs from N(0, I) actions (ρ = 20, T = 100)."""
    n = 512
    env = DesignEnv(n, EnvConfig(resolution=20, steps=100), materials=materials, compute_metrics=False)
    g = torch.Generator().manual_seed(seed)
    volumes, nonempty = [], []
    env.reset()
    for _ in range(episodes // n):
        for _ in range(100):
            _, reward, done, info = env.step(torch.randn(n, 3 + materials, generator=g))
        volumes.append(reward)
        nonempty.append((info["final_grids"] != 0).sum(dim=(1, 2, 3)).float())
    return torch.cat(volumes), torch.cat(nonempty)


def test_untrained_policy_matches_the_paper_volume_task():
    """Paper §IV: an untrained policy puts 11.62 % of the non-empty voxels in the body (k = 2)."""
    volume, nonempty = untrained_bodies(materials=2, episodes=2048, seed=0)
    ratio = (volume / nonempty).mean().item()
    assert ratio == pytest.approx(0.116, abs=0.005)
    assert volume.mean().item() == pytest.approx(41, abs=2.5)
    assert volume.std().item() == pytest.approx(19, abs=3)
    assert nonempty.mean().item() == pytest.approx(340, abs=15)
    assert volume.max().item() <= 800


def test_untrained_policy_locomotion_materials():
    volume, _ = untrained_bodies(materials=4, episodes=1024, seed=1)
    assert volume.mean().item() == pytest.approx(78, abs=5)
