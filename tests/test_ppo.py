"""PPO: the algorithm's pieces against hand-worked values, checkpoints, exact resume, and learning on toy tasks."""

from __future__ import annotations

import math
import pickle
from typing import Any

import numpy as np
import pytest
import torch
from torch.distributions import Normal, kl_divergence

from freeform.agents import PPO, MLPActorCritic, PPOConfig, VoxelActorCritic
from freeform.agents.ppo import (
    clamped_value_loss,
    clipped_surrogate,
    compute_advantages,
    discounted_cumsum,
    explained_variance,
    gaussian_entropy,
    gaussian_kl,
    gaussian_log_prob,
    minibatch_loss,
    minibatch_samples,
    ppo2_value_loss,
    standardize,
    update_kl_coeff,
)
from freeform.envs.base import VecEnv

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# ---------------------------------------------------------------------------------------------------------------
# Toy batched environments, written in torch.
# ---------------------------------------------------------------------------------------------------------------


class PointMassEnv:
    """N point masses in the plane, each to reach its goal in ``horizon`` steps. obs = (position, goal) float [N, 4];
    action = velocity [N, 2] (clipped to ±1, scaled by ``speed``); reward = −distance to the goal, every step."""

    def __init__(self, num_envs: int = 32, horizon: int = 20, speed: float = 0.15) -> None:
        self.num_envs, self.horizon, self.speed = num_envs, horizon, speed
        self.observation_shape, self.action_dim, self.device = (4,), 2, torch.device("cpu")
        self.generator = torch.Generator().manual_seed(0)
        self.pos = torch.zeros(num_envs, 2)
        self.goal = torch.zeros(num_envs, 2)
        self.t = torch.zeros(num_envs, dtype=torch.int64)

    def _new_episode(self, mask: torch.Tensor) -> None:
        n = int(mask.sum())
        self.pos[mask] = torch.rand(n, 2, generator=self.generator) * 2 - 1
        self.goal[mask] = torch.rand(n, 2, generator=self.generator) * 2 - 1
        self.t[mask] = 0

    def _obs(self) -> torch.Tensor:
        return torch.cat([self.pos, self.goal], dim=1)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        if seed is not None:
            self.generator.manual_seed(seed)
        self._new_episode(torch.ones(self.num_envs, dtype=torch.bool))
        return self._obs()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        self.pos = self.pos + self.speed * actions.clamp(-1, 1)
        self.t += 1
        reward = -(self.pos - self.goal).norm(dim=1)
        done = self.t >= self.horizon
        info: dict[str, Any] = {}
        if done.any():
            info["final_distance"] = -reward[done]
            self._new_episode(done)
        return self._obs(), reward, done, info

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state(), "pos": self.pos.clone(), "goal": self.goal.clone(), "t": self.t.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.pos, self.goal, self.t = state["pos"].clone(), state["goal"].clone(), state["t"].clone()


class LooseDtypeEnv(PointMassEnv):
    """PointMassEnv whose rewards are float64 and whose done flags are uint8 (the protocol's loosest)."""

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        obs, reward, done, info = super().step(actions)
        return obs, reward.double(), done.to(torch.uint8), info


class PaintEnv:
    """A miniature of the design environment: a uint8 grid [N, ρ, ρ, ρ] with k materials, starting empty; each action
    [x, y, z, w_0 … w_{k−1}] sets the voxel at f(a) = ½ + clip(a, −2, 2)/4 of each axis to argmax(w); after ``horizon``
    actions the episode ends with reward = number of non-empty voxels (sparse, like the volume task)."""

    def __init__(self, num_envs: int = 16, resolution: int = 4, materials: int = 2, horizon: int = 8) -> None:
        self.num_envs, self.resolution, self.materials, self.horizon = num_envs, resolution, materials, horizon
        self.observation_shape = (resolution,) * 3
        self.action_dim, self.device = 3 + materials, torch.device("cpu")
        self.grids = torch.zeros((num_envs, *self.observation_shape), dtype=torch.uint8)
        self.t = 0

    def reset(self, seed: int | None = None) -> torch.Tensor:
        self.grids.zero_()
        self.t = 0
        return self.grids.clone()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        f = 0.5 + actions.clamp(-2, 2) / 4
        cell = (f[:, :3] * self.resolution).long().clamp(0, self.resolution - 1)
        material = f[:, 3:].argmax(dim=1).to(torch.uint8)
        self.grids[torch.arange(self.num_envs), cell[:, 0], cell[:, 1], cell[:, 2]] = material
        self.t += 1
        reward = torch.zeros(self.num_envs)
        done = torch.full((self.num_envs,), self.t == self.horizon)
        info: dict[str, Any] = {}
        if self.t == self.horizon:
            reward = (self.grids > 0).flatten(1).sum(1).float()
            info["final_grids"] = self.grids.clone()
            self.reset()
        return self.grids.clone(), reward, done, info

    def state_dict(self) -> dict[str, Any]:
        return {"grids": self.grids.clone(), "t": self.t}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.grids, self.t = state["grids"].clone(), state["t"]


def test_toy_envs_follow_the_vecenv_protocol() -> None:
    assert isinstance(PointMassEnv(), VecEnv) and isinstance(PaintEnv(), VecEnv)


# ---------------------------------------------------------------------------------------------------------------
# Pure pieces against hand-worked values.
# ---------------------------------------------------------------------------------------------------------------

GAMMA = 0.99


def test_sparse_reward_returns_are_discounted_final_reward() -> None:
    """Reward r only at the last of T = 4 steps: G_t = γ^(T−1−t) r; advantage = G − V."""
    rewards = torch.tensor([[0.0], [0.0], [0.0], [5.0]])
    dones = torch.tensor([[False], [False], [False], [True]])
    values = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    adv, ret = compute_advantages(rewards, values, dones, torch.tensor([100.0]), GAMMA, 1.0)
    expected = torch.tensor([[5 * GAMMA**3], [5 * GAMMA**2], [5 * GAMMA], [5.0]])
    torch.testing.assert_close(ret, expected)
    torch.testing.assert_close(adv, expected - values)


def test_cut_episode_is_bootstrapped_and_finished_one_is_not() -> None:
    """Env 0 finishes at t = 1 (no bootstrap through the done), then runs on and is cut at T = 3 (bootstrap with
    V(s_T) = 10). Env 1 never finishes: G_t = Σ γ^i r + γ^(T−t)·V(s_T)."""
    rewards = torch.tensor([[1.0, 1.0], [2.0, 0.0], [3.0, 0.0]])
    dones = torch.tensor([[False, False], [True, False], [False, False]])
    values = torch.zeros(3, 2)
    last_value = torch.tensor([10.0, -4.0])
    _, ret = compute_advantages(rewards, values, dones, last_value, GAMMA, 1.0)
    g = GAMMA
    expected = torch.tensor(
        [
            [1 + g * 2, 1 + g**3 * -4],
            [2.0, g**2 * -4],
            [3 + g * 10, g * -4],
        ]
    )
    torch.testing.assert_close(ret, expected)


def test_gae_lambda_matches_hand_computation() -> None:
    r, v, lam = [1.0, 0.0, 2.0], [0.5, 1.5, -1.0], 0.9
    last_v = 3.0
    d = [r[0] + GAMMA * v[1] - v[0], r[1] + GAMMA * v[2] - v[1], r[2] + GAMMA * last_v - v[2]]
    a2 = d[2]
    a1 = d[1] + GAMMA * lam * a2
    a0 = d[0] + GAMMA * lam * a1
    adv, ret = compute_advantages(
        torch.tensor(r)[:, None], torch.tensor(v)[:, None], torch.zeros(3, 1, dtype=torch.bool), torch.tensor([last_v]), GAMMA, lam
    )
    torch.testing.assert_close(adv[:, 0], torch.tensor([a0, a1, a2]))
    torch.testing.assert_close(ret[:, 0], torch.tensor([a0, a1, a2]) + torch.tensor(v))


def _sequential_cumsum(x: np.ndarray, discount: float, starts: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """The recurrence one step at a time, in float64 numpy: the reference for the blocked scan."""
    y, previous = np.zeros_like(x), initial.copy()
    for t in range(len(x)):
        previous = x[t] + discount * np.where(starts[t], 0.0, previous)
        y[t] = previous
    return y


@pytest.mark.parametrize("steps, envs", [(1, 1), (7, 1), (2048, 1), (130, 3), (37, 64), (20, 5000), (65, 70)])
@pytest.mark.parametrize("reverse", [False, True])
def test_discounted_cumsum_is_the_step_by_step_recurrence(steps: int, envs: int, reverse: bool) -> None:
    """The blocked scan against the plain loop, for block lengths from 64 (one env) down to 1 (5,000 envs), rollouts
    that are not a multiple of the block, restarts anywhere (also at t = 0 and at block edges) and a carried value."""
    rng = np.random.default_rng(steps * envs)
    x = rng.normal(size=(steps, envs))
    starts = rng.random((steps, envs)) < 0.05
    starts[0, 0] = True
    starts[min(63, steps - 1), -1] = True
    initial = rng.normal(size=envs)
    got = discounted_cumsum(torch.from_numpy(x), 0.97, torch.from_numpy(starts), torch.from_numpy(initial), reverse)
    flip = (lambda a: a[::-1]) if reverse else (lambda a: a)
    expected = flip(_sequential_cumsum(flip(x), 0.97, flip(starts), initial))
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12, atol=1e-12)


def test_discounted_cumsum_keeps_shape_dtype_and_sums_episodes() -> None:
    """γ = 1 and restarts after each done: the running episode sums (as PPO reports episode returns); trailing
    dims are kept, float32 stays float32, no initial = 0."""
    rewards = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])[:, :, None]  # [T=3, N=2, 1]
    starts = torch.tensor([[False, False], [True, False], [False, True]])[:, :, None]
    got = discounted_cumsum(rewards, 1.0, starts)
    assert got.dtype == torch.float32 and got.shape == (3, 2, 1)
    torch.testing.assert_close(got[:, :, 0], torch.tensor([[1.0, 2.0], [3.0, 6.0], [8.0, 6.0]]))


def test_standardize_over_the_batch_uses_population_std() -> None:
    x = torch.tensor([1.0, 2.0, 3.0, 10.0])
    expected = (np.array([1, 2, 3, 10.0]) - 4.0) / np.std([1, 2, 3, 10.0])
    torch.testing.assert_close(standardize(x), torch.tensor(expected, dtype=torch.float32))
    torch.testing.assert_close(standardize(torch.full((5,), 7.0)), torch.zeros(5))  # constant: no division by 0


def test_clipped_surrogate_hand_cases() -> None:
    ratio = torch.tensor([1.5, 0.5, 0.5, 1.5, 1.1])
    adv = torch.tensor([2.0, 2.0, -1.0, -1.0, 3.0])
    # A>0: capped at (1+ε)A when ρ is large, ρA when small; A<0: capped at (1−ε)A when ρ small, ρA when large.
    expected = torch.tensor([1.3 * 2, 0.5 * 2, -0.7, -1.5, 1.1 * 3])
    torch.testing.assert_close(clipped_surrogate(ratio, adv, 0.3), expected)


def test_value_losses_hand_cases() -> None:
    v, g = torch.tensor([0.0, 3.0, -2.0]), torch.tensor([1.0, 0.0, 2.0])
    torch.testing.assert_close(clamped_value_loss(v, g, 1e5), torch.tensor([1.0, 9.0, 16.0]))
    torch.testing.assert_close(clamped_value_loss(v, g, 5.0), torch.tensor([1.0, 5.0, 5.0]))
    old = torch.tensor([0.5, 0.0, 0.0])
    # Clipped V = old + clip(V − old, ±1) = [0, 1, −1]; loss = max(plain, clipped) = [max(1,1), max(9,1), max(16,9)].
    torch.testing.assert_close(ppo2_value_loss(v, old, g, 1.0), torch.tensor([1.0, 9.0, 16.0]))
    v2 = torch.tensor([2.0])  # old 0, target 1: plain (2−1)² = 1; clipped V = 1 → 0; max = 1
    torch.testing.assert_close(ppo2_value_loss(v2, torch.tensor([0.0]), torch.tensor([1.0]), 1.0), torch.tensor([1.0]))
    v3 = torch.tensor([0.5])  # old 3, target 0.5: plain 0; clipped V = 2 → 2.25
    torch.testing.assert_close(ppo2_value_loss(v3, torch.tensor([3.0]), torch.tensor([0.5]), 1.0), torch.tensor([2.25]))


def test_kl_rule() -> None:
    assert update_kl_coeff(0.2, 0.03, 0.01) == pytest.approx(0.3)
    assert update_kl_coeff(0.2, 0.004, 0.01) == pytest.approx(0.1)
    assert update_kl_coeff(0.2, 0.01, 0.01) == 0.2
    assert update_kl_coeff(0.2, 0.02, 0.01) == 0.2  # the band's edges keep β
    assert update_kl_coeff(0.2, 0.005, 0.01) == 0.2


def test_gaussian_pieces_match_torch_distributions() -> None:
    g = torch.Generator().manual_seed(1)
    m0, s0, m1, s1, x = (torch.randn(7, 5, generator=g) for _ in range(5))
    p, q = Normal(m0, s0.exp()), Normal(m1, s1.exp())
    torch.testing.assert_close(gaussian_log_prob(x, m0, s0), p.log_prob(x).sum(-1))
    torch.testing.assert_close(gaussian_entropy(s0), p.entropy().sum(-1))
    torch.testing.assert_close(gaussian_kl(m0, s0, m1, s1), kl_divergence(p, q).sum(-1))


def test_explained_variance() -> None:
    y = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert explained_variance(y, y) == pytest.approx(1.0)
    assert explained_variance(torch.full((4,), 2.5), y) == pytest.approx(0.0)
    assert math.isnan(explained_variance(y, torch.ones(4)))


@pytest.mark.parametrize(
    "field,value",
    [("lr", 0.0), ("gamma", 1.5), ("gae_lambda", -0.1), ("clip_param", 0), ("kl_coeff", -1.0), ("num_sgd_iter", 0),
     ("sgd_minibatch_size", 2.5), ("rollout_steps", 0), ("grad_clip", 0.0), ("advantage_norm", "episode"),
     ("value_clip", "huber"), ("lr_schedule", "cosine"), ("device", "tpu:banana"), ("vf_clip_param", -1.0)],
)
def test_config_validation_names_the_field(field: str, value: Any) -> None:
    with pytest.raises(ValueError, match=field):
        PPOConfig(**{field: value})


def test_default_config_is_the_papers_semantics() -> None:
    cfg = PPOConfig()
    assert (cfg.gamma, cfg.gae_lambda, cfg.clip_param, cfg.kl_coeff, cfg.kl_target) == (0.99, 1.0, 0.3, 0.2, 0.01)
    assert (cfg.vf_loss_coeff, cfg.vf_clip_param, cfg.entropy_coeff, cfg.grad_clip) == (1.0, 1e5, 0.0, None)
    assert (cfg.advantage_norm, cfg.value_clip, cfg.lr, cfg.sgd_minibatch_size) == ("batch", "squared", 1e-4, 128)


# ---------------------------------------------------------------------------------------------------------------
# The loop: storage, statistics, the KL schedule.
# ---------------------------------------------------------------------------------------------------------------


def small_paint_ppo(**overrides: Any) -> PPO:
    env = PaintEnv(num_envs=8, resolution=4, materials=2, horizon=6)
    cfg = dict(rollout_steps=9, num_sgd_iter=2, sgd_minibatch_size=16, lr=1e-3, seed=3)
    cfg.update(overrides)
    torch.manual_seed(0)  # the network's init comes from the global RNG: pin it so no test depends on test order
    return PPO(env, VoxelActorCritic(resolution=4, materials=2, hidden=16), PPOConfig(**cfg))


def test_rollout_storage_shapes_dtypes_and_episode_infos() -> None:
    ppo = small_paint_ppo()
    stats = ppo.train_epoch()
    ro = ppo.rollout
    assert ro.obs.shape == (9, 8, 4, 4, 4) and ro.obs.dtype == torch.uint8
    assert ro["actions"].shape == (9, 8, 5) and ro.logprobs.shape == ro.rewards.shape == ro.values.shape == (9, 8)
    assert ro.dones.dtype == torch.bool and ro.dones[5].all() and ro.dones.sum() == 8
    assert (ro.obs[0] == 0).all() and (ro.obs[6] == 0).all()  # fresh episodes start empty
    assert len(ppo.episode_infos) == 1 and ppo.episode_infos[0]["final_grids"].shape == (8, 4, 4, 4)
    # The episode reward is the sparse final reward, the same the env reported.
    final_volume = (ppo.episode_infos[0]["final_grids"] > 0).flatten(1).sum(1).float()
    torch.testing.assert_close(ro.rewards[5], final_volume)
    assert stats["episodes"] == 8 and stats["episode_reward_mean"] == pytest.approx(final_volume.mean().item())
    assert stats["episode_reward_max"] == final_volume.max() and stats["episode_reward_min"] == final_volume.min()
    assert ppo.global_step == 72 and ppo.epoch == 1
    required = {"episode_reward_mean", "episode_reward_max", "episode_reward_min", "episodes", "policy_loss",
                "value_loss", "approx_kl", "kl_coeff", "entropy", "clip_fraction", "explained_variance",
                "samples_per_second", "time_rollout", "time_env", "time_update", "action_std",
                "action_std_position", "action_std_material"}
    assert required <= stats.keys()
    assert all(isinstance(v, float) for v in stats.values())


def test_cut_episode_bootstrap_in_the_loop() -> None:
    """Episodes of 6 steps, rollouts of 9: steps 6..8 are cut and bootstrapped with V(s_9); steps 0..5 are not."""
    ppo = small_paint_ppo()
    ppo.collect()  # collection only: the policy is still the one that valued the rollout
    ro = ppo.rollout
    last_value = ppo.policy(ppo.obs)[2].detach()
    torch.testing.assert_close(ro.last_value, last_value)
    torch.testing.assert_close(ro.returns[8], GAMMA * last_value)
    torch.testing.assert_close(ro.returns[6], GAMMA**3 * last_value)
    torch.testing.assert_close(ro.returns[0], GAMMA**5 * ro.rewards[5])
    torch.testing.assert_close(ro.advantages, ro.returns - ro.values)


def test_first_update_statistics_against_hand_computation() -> None:
    """One pass, one minibatch = the whole batch: at the first step π = π_old, so ratio = 1, KL = 0, nothing is
    clipped, the policy loss is −mean(standardised A) = 0, and the value loss is mean((V − G)²)."""
    import copy

    ppo = small_paint_ppo(num_sgd_iter=1, sgd_minibatch_size=72)
    ppo.collect()
    before = copy.deepcopy(ppo.policy)
    stats = ppo.update()
    ro = ppo.rollout
    with torch.no_grad():
        _, log_std, value = before(ro.obs.reshape(72, 4, 4, 4))
    expected_value_loss = (value - ro.returns.reshape(-1)).square().mean().item()
    assert stats["value_loss"] == pytest.approx(expected_value_loss, rel=1e-5)
    assert stats["total_loss"] == pytest.approx(stats["policy_loss"] + expected_value_loss, rel=1e-5)
    assert abs(stats["policy_loss"]) < 1e-6 and stats["approx_kl"] == 0.0 and stats["clip_fraction"] == 0.0
    assert stats["entropy"] == pytest.approx(gaussian_entropy(log_std).mean().item(), rel=1e-5)
    assert ppo.kl_coeff == pytest.approx(0.1)  # KL 0 < target / 2 halves β


@pytest.mark.parametrize(
    "variant",
    [{"advantage_norm": "minibatch"}, {"advantage_norm": "none"}, {"value_clip": "ppo2", "vf_clip_param": 0.5},
     {"grad_clip": 0.5, "entropy_coeff": 0.01}, {"kl_coeff": 0.0}, {"gae_lambda": 0.9}],
)
def test_variants_train(variant: dict[str, Any]) -> None:
    ppo = small_paint_ppo(**variant)
    before = [p.detach().clone() for p in ppo.policy.parameters()]
    stats = ppo.learn(2)[-1]
    assert all(math.isfinite(stats[k]) for k in ("policy_loss", "value_loss", "approx_kl", "entropy"))
    assert any(not torch.equal(a, b) for a, b in zip(before, ppo.policy.parameters(), strict=True))
    if variant.get("kl_coeff") == 0.0:
        assert ppo.kl_coeff == 0.0


def test_linear_lr_schedule() -> None:
    ppo = small_paint_ppo(lr_schedule="linear", lr_anneal_epochs=4, lr=1e-3)
    lrs = [s["lr"] for s in ppo.learn(5)]
    assert lrs == pytest.approx([1e-3, 7.5e-4, 5e-4, 2.5e-4, 0.0])
    assert ppo.optimizer.param_groups[0]["lr"] == 0.0


def test_kl_coeff_follows_the_rule_after_each_epoch() -> None:
    ppo = small_paint_ppo(lr=3e-3, num_sgd_iter=3)
    for _ in range(3):
        before = ppo.kl_coeff
        stats = ppo.train_epoch()
        assert stats["kl_coeff"] == before
        assert ppo.kl_coeff == pytest.approx(update_kl_coeff(before, stats["approx_kl"], 0.01))


def test_logger_and_callback() -> None:
    logged: list[tuple[dict, int]] = []

    class Log:
        def log(self, stats: dict[str, float], step: int) -> None:
            logged.append((stats, step))

    ppo = small_paint_ppo()
    ppo.logger = Log()
    history = ppo.learn(5, callback=lambda p, s: p.epoch < 2)
    assert len(history) == 2 and [step for _, step in logged] == [72, 144]


def test_policy_that_does_not_fit_the_env_is_rejected() -> None:
    env = PaintEnv(num_envs=4, resolution=4, materials=2)
    with pytest.raises(ValueError, match="gives 6 numbers per action but the env takes 5"):
        PPO(env, VoxelActorCritic(resolution=4, materials=3, hidden=8))  # 3 + 3 action dims, env has 3 + 2
    with pytest.raises(ValueError, match="policy cannot read"):
        PPO(env, VoxelActorCritic(resolution=6, materials=2, hidden=8))

    class MeanOnly(torch.nn.Module):  # declares nothing: PPO takes a Gaussian over the env's 5 numbers
        def __init__(self) -> None:
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(5))

        def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            return self.w.expand(obs.shape[0], 5), obs.new_zeros(obs.shape[0], dtype=torch.float32)

    with pytest.raises(ValueError, match=r"policy must return its DiagGaussian\(dim=5\) parameters \(\[4, 5\], \[4, 5\]\)"):
        PPO(env, MeanOnly())


def test_act_shapes_and_determinism() -> None:
    ppo = small_paint_ppo()
    obs = torch.zeros(8, 4, 4, 4, dtype=torch.uint8)
    a = ppo.act(obs, deterministic=True)
    assert a.shape == (8, 5)
    torch.testing.assert_close(a, ppo.policy(obs)[0])
    assert not torch.equal(ppo.act(obs), ppo.act(obs))


# ---------------------------------------------------------------------------------------------------------------
# Checkpoints and exact resume.
# ---------------------------------------------------------------------------------------------------------------


def point_mass_ppo(seed: int = 0) -> PPO:
    env = PointMassEnv(num_envs=16, horizon=7)
    cfg = PPOConfig(rollout_steps=10, num_sgd_iter=3, sgd_minibatch_size=40, lr=1e-3, seed=seed)
    torch.manual_seed(seed)  # the policy's initial weights come from the global RNG, as for any nn.Module
    return PPO(env, MLPActorCritic(4, 2, hidden=(16, 16)), cfg)


def _comparable(stats: dict[str, float]) -> dict[str, float]:
    return {k: v for k, v in stats.items() if not (k.startswith("time_") or k == "samples_per_second")}


def test_save_load_round_trip(tmp_path: Any) -> None:
    ppo = point_mass_ppo()
    ppo.train_epoch()
    path = tmp_path / "ckpt.pt"
    ppo.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temp file left behind
    loaded = PPO.load(path, PointMassEnv(num_envs=16, horizon=7))
    assert type(loaded.policy) is MLPActorCritic and loaded.policy.init_kwargs == ppo.policy.init_kwargs
    assert loaded.config == ppo.config
    assert (loaded.epoch, loaded.global_step, loaded.kl_coeff) == (ppo.epoch, ppo.global_step, ppo.kl_coeff)
    for a, b in zip(ppo.policy.state_dict().values(), loaded.policy.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert torch.equal(loaded.obs, ppo.obs) and torch.equal(loaded.env.pos, ppo.env.pos)


def test_voxel_policy_checkpoint_rebuilds_from_file(tmp_path: Any) -> None:
    ppo = small_paint_ppo()
    ppo.save(tmp_path / "v.pt")
    loaded = PPO.load(tmp_path / "v.pt", PaintEnv(num_envs=8, resolution=4, materials=2, horizon=6))
    assert isinstance(loaded.policy, VoxelActorCritic) and loaded.policy.hidden == 16
    grid = torch.randint(0, 2, (3, 4, 4, 4), dtype=torch.uint8)
    for a, b in zip(ppo.policy(grid), loaded.policy(grid), strict=True):
        assert torch.equal(a, b)


def test_load_rejects_corrupt_and_incompatible_files(tmp_path: Any) -> None:
    ppo = point_mass_ppo()
    good = tmp_path / "good.pt"
    ppo.save(good)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:1000])
    with pytest.raises(ValueError, match="truncated.pt"):
        PPO.load(truncated, PointMassEnv(num_envs=16))
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ValueError, match="foreign.pt"):
        PPO.load(foreign, PointMassEnv(num_envs=16))
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(pickle.dumps("hello") + b"\x00" * 10)
    with pytest.raises(ValueError, match="garbage.pt"):
        PPO.load(garbage, PointMassEnv(num_envs=16))
    with pytest.raises(ValueError, match="good.pt"):
        PPO.load(good, PointMassEnv(num_envs=8))  # wrong number of envs
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        PPO.load(tmp_path / "missing.pt", PointMassEnv(num_envs=16))


def test_resume_is_bit_for_bit(tmp_path: Any) -> None:
    """Two epochs straight = one epoch, save, load into a fresh object (fresh env), one epoch."""
    straight = point_mass_ppo(seed=5)
    s1 = straight.train_epoch()
    s2 = straight.train_epoch()

    first = point_mass_ppo(seed=5)
    r1 = first.train_epoch()
    first.save(tmp_path / "resume.pt")
    del first
    resumed = PPO.load(tmp_path / "resume.pt", PointMassEnv(num_envs=16, horizon=7))
    r2 = resumed.train_epoch()

    assert _comparable(s1) == _comparable(r1)
    assert _comparable(s2) == _comparable(r2)
    for a, b in zip(straight.policy.parameters(), resumed.policy.parameters(), strict=True):
        assert torch.equal(a, b)
    for name in ("obs", "actions", "rewards", "values", "logprobs"):
        assert torch.equal(straight.rollout[name], resumed.rollout[name])
    assert straight.kl_coeff == resumed.kl_coeff and straight.global_step == resumed.global_step


def test_resume_is_bit_for_bit_on_the_design_env(tmp_path: Any) -> None:
    """The same with DesignEnv (its own state_dict) and the paper's network on its fast CPU trunk."""
    design = pytest.importorskip("freeform.envs.design")

    def build() -> PPO:
        torch.manual_seed(7)
        env = design.DesignEnv(8, design.EnvConfig(resolution=8, steps=6), materials=4, compute_metrics=False)
        cfg = PPOConfig(rollout_steps=4, num_sgd_iter=2, sgd_minibatch_size=8, lr=1e-3, seed=7)  # episodes cut
        return PPO(env, VoxelActorCritic(resolution=8, materials=4, hidden=16), cfg)

    straight = build()
    straight.learn(3)
    first = build()
    first.learn(2)
    first.save(tmp_path / "design.pt")
    resumed = PPO.load(tmp_path / "design.pt", design.DesignEnv(8, design.EnvConfig(resolution=8, steps=6),
                                                                materials=4, compute_metrics=False))
    resumed.train_epoch()
    for a, b in zip(straight.policy.parameters(), resumed.policy.parameters(), strict=True):
        assert torch.equal(a, b)
    assert torch.equal(straight.rollout.obs, resumed.rollout.obs) and torch.equal(straight.obs, resumed.obs)


# ---------------------------------------------------------------------------------------------------------------
# Learning.
# ---------------------------------------------------------------------------------------------------------------


def test_ppo_learns_point_mass_reaching() -> None:
    """From a random policy (return ≈ −22) to one that heads for the goal (≈ −5; the best possible is ≈ −3)."""
    torch.manual_seed(0)
    env = PointMassEnv(num_envs=32, horizon=20)
    cfg = PPOConfig(rollout_steps=64, num_sgd_iter=8, sgd_minibatch_size=512, lr=3e-3, gae_lambda=0.95, seed=0)
    ppo = PPO(env, MLPActorCritic(4, 2, hidden=(64, 64)), cfg)
    history = ppo.learn(30)
    first = history[0]["episode_reward_mean"]
    last = np.mean([h["episode_reward_mean"] for h in history[-3:]])
    assert first < -15.0
    assert last > -6.5, (first, last)  # seeds 0-2 reach -5.1 ... -5.3


def test_ppo_improves_paint_volume_with_the_voxel_network() -> None:
    """The paper's network and default PPO semantics on a miniature volume task: reward = filled voxels."""
    torch.manual_seed(0)
    env = PaintEnv(num_envs=32, resolution=4, materials=2, horizon=8)
    cfg = PPOConfig(rollout_steps=8, num_sgd_iter=8, sgd_minibatch_size=64, lr=1e-3, seed=0)
    ppo = PPO(env, VoxelActorCritic(resolution=4, materials=2, hidden=32), cfg)
    history = ppo.learn(25)
    first = history[0]["episode_reward_mean"]
    last = np.mean([h["episode_reward_mean"] for h in history[-3:]])
    assert first < 6.0 and last > 6.5, (first, last)  # at most 8 voxels can be filled


def test_ppo_improves_the_volume_reward_of_the_design_env() -> None:
    """The real pipeline at a tiny size: DesignEnv (ρ = 8, k = 2, T = 10) + VolumeTask + the paper's network."""
    design = pytest.importorskip("freeform.envs.design")
    from freeform.envs.tasks import VolumeTask

    torch.manual_seed(0)
    env = design.DesignEnv(32, design.EnvConfig(resolution=8, steps=10),
                           materials=2, task=VolumeTask(), compute_metrics=False)
    cfg = PPOConfig(rollout_steps=10, num_sgd_iter=10, sgd_minibatch_size=64, lr=3e-4, seed=0)
    ppo = PPO(env, VoxelActorCritic(resolution=8, materials=2, hidden=32), cfg)
    history = ppo.learn(18)
    assert ppo.rollout.obs.dtype == torch.uint8 and len(ppo.episode_infos) == 1
    first = history[0]["episode_reward_mean"]
    last = np.mean([h["episode_reward_mean"] for h in history[-3:]])
    assert last > first + 10.0, (first, last)  # random designs: ≈ 17 voxels in the body; trained: ≈ 35-40


# ---------------------------------------------------------------------------------------------------------------
# The flat parameter vector (freeform.agents.ppo.flat_params) against torch's per-tensor Adam and clipping.
# ---------------------------------------------------------------------------------------------------------------


def _two_identical_mlps() -> tuple[MLPActorCritic, MLPActorCritic]:
    torch.manual_seed(3)
    a = MLPActorCritic(5, 2, hidden=(16, 16))
    b = MLPActorCritic(5, 2, hidden=(16, 16))
    b.load_state_dict(a.state_dict())
    return a, b


def _mlp_loss(policy: MLPActorCritic, obs: torch.Tensor) -> torch.Tensor:
    mean, log_std, value = policy(obs)
    return (mean - 1.0).square().mean() + log_std.sum() + value.square().mean()


@pytest.mark.parametrize("impl", ["foreach", "fused"])
def test_flat_parameters_give_torchs_per_tensor_adam_bit_for_bit(impl: str) -> None:
    """Adam over the flat vector (gradients accumulated into its views, zeroed in place) = torch's Adam over the
    module's own tensors, for 5 steps; the module's parameters and state dict are still its own."""
    from freeform.agents.ppo.flat_params import FlatParameters

    ours, reference = _two_identical_mlps()
    flat = FlatParameters(ours.parameters())
    names = [name for name, _ in ours.named_parameters()]
    assert all(p.data_ptr() >= flat.value.data_ptr() for p in ours.parameters()) and flat.value.numel() == sum(
        p.numel() for p in reference.parameters())
    opt_ours = torch.optim.Adam([flat.value], lr=1e-2, **{impl: True})
    opt_ref = torch.optim.Adam(reference.parameters(), lr=1e-2, **{impl: True})
    obs = torch.randn(32, 5, generator=torch.Generator().manual_seed(0))
    for _ in range(5):
        flat.zero_grad()
        _mlp_loss(ours, obs).backward()
        opt_ours.step()
        opt_ref.zero_grad()
        _mlp_loss(reference, obs).backward()
        opt_ref.step()
    for name, a, b in zip(names, ours.parameters(), reference.parameters(), strict=True):
        assert torch.equal(a, b), name
    assert list(ours.state_dict()) == list(reference.state_dict())


def test_flat_gradient_clipping_matches_torchs() -> None:
    from freeform.agents.ppo.flat_params import FlatParameters

    ours, reference = _two_identical_mlps()
    flat = FlatParameters(ours.parameters())
    obs = torch.randn(32, 5, generator=torch.Generator().manual_seed(1)) * 10
    for policy in (ours, reference):
        _mlp_loss(policy, obs).backward()
    total = flat.clip_grad_norm_(0.5)
    expected = torch.nn.utils.clip_grad_norm_(list(reference.parameters()), 0.5)
    torch.testing.assert_close(total, expected)
    assert total > 0.5  # the clip did act
    for a, b in zip(ours.parameters(), reference.parameters(), strict=True):
        torch.testing.assert_close(a.grad, b.grad)


def test_flat_parameters_survive_zero_grad_and_refuse_a_moved_policy() -> None:
    from freeform.agents.ppo.flat_params import FlatParameters

    ours, _ = _two_identical_mlps()
    flat = FlatParameters(ours.parameters())
    ours.zero_grad()  # torch's default: gradients set to None
    flat.check()  # … re-seated as views of the flat gradient
    _mlp_loss(ours, torch.ones(4, 5)).backward()
    assert flat.grad.abs().sum() > 0
    ours.double()
    with pytest.raises(RuntimeError, match="replaced after PPO was built"):
        flat.check()


@pytest.mark.parametrize("frozen", [False, True])
def test_optimizer_state_saved_per_tensor_loads_into_the_flat_adam(frozen: bool) -> None:
    """A checkpoint written before the flat vector (Adam over every module tensor, a frozen one without moments)
    resumes the same training."""
    from freeform.agents.ppo.flat_params import FlatParameters

    ours, reference = _two_identical_mlps()
    for policy in (ours, reference):
        policy.actor[0].bias.requires_grad_(not frozen)
    opt_ref = torch.optim.Adam(reference.parameters(), lr=1e-2, foreach=True)
    obs = torch.randn(16, 5, generator=torch.Generator().manual_seed(2))
    for _ in range(3):
        opt_ref.zero_grad()
        _mlp_loss(reference, obs).backward()
        opt_ref.step()
    ours.load_state_dict(reference.state_dict())
    flat = FlatParameters(ours.parameters())
    opt_ours = torch.optim.Adam([flat.value], lr=1e-2, foreach=True)
    saved = pickle.loads(pickle.dumps(opt_ref.state_dict()))  # as read from a file: no tensor shared with opt_ref
    opt_ours.load_state_dict(flat.optimizer_state(saved))
    for policy, opt, zero in ((ours, opt_ours, flat.zero_grad), (reference, opt_ref, opt_ref.zero_grad)):
        zero()
        _mlp_loss(policy, obs).backward()
        opt.step()
    for a, b in zip(ours.parameters(), reference.parameters(), strict=True):
        assert torch.equal(a, b)
    short = {"state": saved["state"], "param_groups": [{**saved["param_groups"][0], "params": list(range(5))}]}
    with pytest.raises(ValueError, match="parameter tensors"):
        flat.optimizer_state(short)
    saved["state"].pop(3)
    with pytest.raises(ValueError, match="some trainable parameters but not others"):
        flat.optimizer_state(saved)


def test_an_env_that_writes_its_last_observation_in_place_is_refused() -> None:
    """PPO keeps each step's observation until its rollout ends: an env that hands back the same tensor, updated
    in place, would silently make every stored observation the last one."""

    class InPlace(PointMassEnv):
        def reset(self, seed: int | None = None) -> torch.Tensor:
            self.buffer = super().reset(seed)
            return self.buffer

        def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
            obs, reward, done, info = super().step(actions)
            self.buffer.copy_(obs)
            return self.buffer, reward, done, info

    torch.manual_seed(0)
    ppo = PPO(InPlace(num_envs=4), MLPActorCritic(4, 2, hidden=(8,)), PPOConfig(rollout_steps=4, num_sgd_iter=1))
    with pytest.raises(ValueError, match="written in place"):
        ppo.collect()
    torch.manual_seed(0)
    PPO(PointMassEnv(num_envs=4), MLPActorCritic(4, 2, hidden=(8,)), PPOConfig(rollout_steps=4, num_sgd_iter=1)).collect()


@pytest.mark.parametrize("num_envs", [8, 3])
def test_collect_draws_the_rollouts_noise_in_one_call(num_envs: int) -> None:
    """action = μ + σ·ε with ε the rollout's [T, N, A] drawn in one call from PPO's generator; for N·A = 16 that equals
    T per-step draws of [N, A] on the CPU (the design env's rollouts kept their stream), for N·A = 6 it does not."""
    T = 5
    ppo = PPO(PointMassEnv(num_envs=num_envs), MLPActorCritic(4, 2, hidden=(8,)),
              PPOConfig(rollout_steps=T, num_sgd_iter=1, seed=3))
    g = torch.Generator().manual_seed(0)
    g.set_state(ppo.generator.get_state())
    ppo.collect()
    ro = ppo.rollout
    noise = torch.randn((T, num_envs, 2), generator=g)
    torch.testing.assert_close(ro.actions, ro.means + ro.log_stds.exp() * noise)
    assert torch.equal(g.get_state(), ppo.generator.get_state())  # nothing else drew during the rollout
    g.set_state(torch.Generator().manual_seed(0).get_state())
    per_step = torch.stack([torch.randn((num_envs, 2), generator=g) for _ in range(T)])
    g.manual_seed(0)
    assert torch.equal(per_step, torch.randn((T, num_envs, 2), generator=g)) == (num_envs * 2 % 16 == 0)


def test_collect_casts_an_envs_float64_rewards_and_uint8_dones() -> None:
    ppo = PPO(LooseDtypeEnv(num_envs=4, horizon=3), MLPActorCritic(4, 2, hidden=(8,)),
              PPOConfig(rollout_steps=6, num_sgd_iter=1))
    ppo.collect()
    assert ppo.rollout.rewards.dtype == torch.float32 and ppo.rollout.dones.dtype == torch.bool
    assert ppo.rollout.dones[:, 0].tolist() == [False, False, True, False, False, True]
    assert (ppo.rollout.rewards < 0).all()  # −distance, every step


@pytest.mark.parametrize("overrides", [{}, {"kl_coeff": 0.0, "advantage_norm": "minibatch", "value_clip": "ppo2"}])
def test_compiled_minibatch_loss_trains_as_the_eager_one(overrides: dict[str, Any]) -> None:
    """``compile=True`` runs the same loss through ``torch.compile`` (the KL penalty's β a tensor input): one
    minibatch's gradient equals eager's (Adam's step is nearly scale-free, so the trained weights alone would not
    catch a gradient counted twice), and after two epochs the weights, β and the statistics equal eager's up to float
    rounding, the weights having moved."""
    runs = []
    for compile_ in (False, True):
        env = PointMassEnv(num_envs=16, horizon=7)
        cfg = PPOConfig(rollout_steps=10, num_sgd_iter=3, sgd_minibatch_size=40, lr=1e-3, grad_clip=0.5,
                        compile=compile_, **overrides)
        torch.manual_seed(0)
        ppo = PPO(env, MLPActorCritic(4, 2, hidden=(16, 16)), cfg)
        start = ppo.flat.value.detach().clone()
        stats = [ppo.train_epoch() for _ in range(2)]
        runs.append((start, ppo.flat.value.detach().clone(), ppo.kl_coeff, stats))
        if compile_:  # the first minibatch of the last rollout, at the trained weights, through both paths
            buf, grads = ppo.rollout, []
            samples = minibatch_samples(buf.actions.flatten(0, 1), [p.flatten(0, 1) for p in buf.params],
                                        buf.logprobs.flatten(), buf.values.flatten(), buf.returns.flatten())[:40]
            for loss_fn in (minibatch_loss, ppo._minibatch_loss):
                ppo.flat.zero_grad()
                kl = torch.tensor(ppo.kl_coeff) if ppo.kl_coeff > 0 else None
                loss_fn(ppo.policy, ppo.distribution, cfg, buf.obs.flatten(0, 1)[:40], samples, buf.advantages.flatten()[:40], kl,
                        torch.mean)[0].backward()
                grads.append(ppo.flat.grad.clone())
            assert grads[0].abs().max() > 0
            torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-6)
    (start, eager, beta, eager_stats), (start_c, compiled, beta_c, compiled_stats) = runs
    assert torch.equal(start, start_c)
    assert (eager - start).abs().max() > 1e-3  # the updates did something to compare
    torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-5)
    assert beta_c == pytest.approx(beta)
    for e, c in zip(eager_stats, compiled_stats, strict=True):
        for key in ("policy_loss", "value_loss", "approx_kl", "entropy", "clip_fraction", "total_loss"):
            assert c[key] == pytest.approx(e[key], rel=1e-3, abs=1e-6), key


def test_compiled_instances_do_not_recompile_one_another() -> None:
    """Every PPO with ``compile=True`` keeps its own compiled loss: with torch's recompile limit at 1, a second
    instance (another policy, so other guards) still compiles instead of falling back to eager unannounced (a
    shared code object's cache would be full after the first)."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    with torch._dynamo.config.patch(recompile_limit=1):
        for _ in range(2):
            before = counters["stats"]["unique_graphs"]
            torch.manual_seed(0)
            ppo = PPO(PointMassEnv(num_envs=4, horizon=3), MLPActorCritic(4, 2, hidden=(8,)),
                      PPOConfig(rollout_steps=4, num_sgd_iter=1, sgd_minibatch_size=16, compile=True))
            ppo.train_epoch()
            assert counters["stats"]["unique_graphs"] > before  # this instance's loss was compiled


def test_cuda_graph_is_refused_where_it_cannot_run() -> None:
    """``cuda_graph`` needs a CUDA device and one process, and excludes ``compile``: each refusal names the key (the
    graph itself is checked against the eager update on a GPU: tests/test_cuda.py)."""
    with pytest.raises(ValueError, match="cuda_graph"):
        PPOConfig(cuda_graph=True, compile=True)
    with pytest.raises(ValueError, match="agent.cuda_graph needs a CUDA device"):
        PPO(PointMassEnv(num_envs=4, horizon=3), MLPActorCritic(4, 2, hidden=(8,)), PPOConfig(cuda_graph=True))


def test_the_checkpointed_optimizer_state_is_the_eager_adams() -> None:
    """One checkpoint format whichever way the update runs: the eager Adam's state dict is saved as it is (a float
    lr, the step count on the CPU), and loading it back leaves the optimizer as it was."""
    ppo = PPO(PointMassEnv(num_envs=4, horizon=3), MLPActorCritic(4, 2, hidden=(8,)),
              PPOConfig(rollout_steps=4, num_sgd_iter=1, sgd_minibatch_size=8))
    ppo.train_epoch()
    saved = ppo.state_dict()["optimizer"]
    group = saved["param_groups"][0]
    assert isinstance(group["lr"], float) and not group["capturable"] and saved["state"][0]["step"].device.type == "cpu"
    ppo.load_state_dict(ppo.state_dict())
    assert ppo.optimizer.param_groups[0]["lr"] == group["lr"] and not ppo.optimizer.param_groups[0]["capturable"]
    torch.testing.assert_close(ppo.optimizer.state_dict()["state"][0], saved["state"][0], rtol=0, atol=0)


def test_a_loaded_state_shares_no_tensor_with_its_source() -> None:
    """``b.load_state_dict(a.state_dict())`` in memory, then both train: b's Adam moments are its own (torch's
    optimizer load keeps a tensor already on the right device, which would make a and b train the same moments)."""
    def make() -> PPO:
        torch.manual_seed(0)
        return PPO(PointMassEnv(num_envs=4, horizon=3), MLPActorCritic(4, 2, hidden=(8,)),
                   PPOConfig(rollout_steps=4, num_sgd_iter=1, sgd_minibatch_size=8))

    a, b = make(), make()
    a.train_epoch()
    b.load_state_dict(a.state_dict())
    moments = b.optimizer.state_dict()["state"][0]["exp_avg"].clone()
    a.train_epoch()
    assert torch.equal(b.optimizer.state_dict()["state"][0]["exp_avg"], moments)
