"""Observation groups: a ``Dict`` observation of ``"policy"`` and ``"critic"`` — the actor reads only ``"policy"``,
the critic both, each group normalised by its own statistics (checked against numpy over every observation the env
gave), checkpoints resume bit for bit, an exported actor takes ``"policy"`` alone, and a network whose actor would
read the critic's group is refused."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch
from helpers import learned_straight_and_resumed

from freeform.agents import PPO, GroupedMLPActorCritic, MLPActorCritic, PPOConfig

gym = pytest.importorskip("gymnasium")
from freeform.envs import from_gymnasium  # noqa: E402
from freeform.envs.partial import HideEntries  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py


def cartpole(num_envs: int = 2, critic: bool = True, seed: int = 0) -> Any:
    """CartPole-v1 whose actor sees position and angle; the velocities go to the critic (``critic=True``)."""
    vec = gym.vector.SyncVectorEnv([lambda: HideEntries(gym.make("CartPole-v1"), [1, 3], critic=critic)] * num_envs,
                                   autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    return from_gymnasium(vec, seed=seed, dict_obs=critic)


def config(**overrides: Any) -> PPOConfig:
    return PPOConfig.cleanrl_discrete(**{"rollout_steps": 32, "sgd_minibatch_size": 32, "num_sgd_iter": 2, **overrides})


class Recorder:
    """A VecEnv passed through, keeping every observation it gives (what obs_norm's statistics fold in)."""

    def __init__(self, env: Any) -> None:
        self.env, self.seen = env, []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.env, name)

    def reset(self, seed: int | None = None) -> Any:
        obs = self.env.reset(seed=seed)
        self.seen.append({k: v.clone() for k, v in obs.items()})
        return obs

    def step(self, actions: torch.Tensor) -> Any:
        obs, *rest = self.env.step(actions)
        self.seen.append({k: v.clone() for k, v in obs.items()})
        return (obs, *rest)


def test_the_grouped_network_reads_policy_for_the_actor_and_both_for_the_critic() -> None:
    torch.manual_seed(0)
    net = MLPActorCritic.for_env(cartpole())
    assert isinstance(net, GroupedMLPActorCritic) and net.critic[0].in_features == 4 and net.actor[0].in_features == 2
    obs = {"policy": torch.randn(5, 2), "critic": torch.randn(5, 2)}
    other = {"policy": obs["policy"], "critic": obs["critic"] + 1.0}
    assert torch.equal(net.action_params(obs)[0], net.action_params(other)[0])
    assert not torch.equal(net.value(obs), net.value(other))


def test_each_group_is_normalised_by_its_own_statistics() -> None:
    env = Recorder(cartpole())
    torch.manual_seed(0)
    ppo = PPO(env, MLPActorCritic.for_env(env), config(obs_norm=True))
    ppo.learn(2)
    assert set(ppo.obs_rms) == {"policy", "critic"}
    for key, rms in ppo.obs_rms.items():  # the running moments against numpy's over everything the env gave
        seen = np.concatenate([obs[key].numpy() for obs in env.seen]).astype(np.float64)
        np.testing.assert_allclose(rms.mean.numpy(), seen.mean(0), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(rms.var.numpy(), seen.var(0), rtol=1e-3, atol=1e-4)
    means = {k: r.mean for k, r in ppo.obs_rms.items()}
    assert not torch.allclose(means["policy"], means["critic"])  # two sets of statistics, not one
    stored = ppo.rollout.obs  # what the policy saw: each group by its own statistics
    assert set(stored) == {"policy", "critic"} and stored["policy"].dtype == torch.float32


def test_an_actor_that_reads_the_critics_group_is_refused() -> None:
    class Peeking(GroupedMLPActorCritic):
        def action_params(self, obs: Any) -> tuple[torch.Tensor, ...]:
            return MLPActorCritic.action_params(self, obs["policy"] + obs["critic"])

    class Joint(torch.nn.Module):  # no action_params: its actor cannot run without the critic's inputs
        def forward(self, obs: Any) -> tuple[torch.Tensor, ...]:
            return obs["policy"].new_zeros(obs["policy"].shape[0], 2), obs["critic"].sum(1)

    env = cartpole()
    with pytest.raises(ValueError, match="may read only the 'policy' group"):
        PPO(env, Peeking(2, 2, distribution=env.action_distribution), config())
    with pytest.raises(ValueError, match="must run its actor apart from its critic"):
        PPO(env, Joint(), config())


class DriftEnv:
    """N points on a line pushed by a hidden drift each episode; the actor sees its position, the critic also the
    drift. obs = {"policy": [N, 1], "critic": [N, 1]}; action [N, 1] a velocity; reward −|position|; 12 steps."""

    def __init__(self, num_envs: int = 4) -> None:
        self.num_envs, self.action_dim, self.device = num_envs, 1, torch.device("cpu")
        self.observation_shape = {"policy": (1,), "critic": (1,)}
        self.generator = torch.Generator().manual_seed(0)
        self.pos, self.drift = torch.zeros(num_envs, 1), torch.zeros(num_envs, 1)
        self.t = torch.zeros(num_envs, dtype=torch.int64)

    def _new(self, mask: torch.Tensor) -> None:
        self.pos[mask] = torch.rand(int(mask.sum()), 1, generator=self.generator) * 2 - 1
        self.drift[mask] = torch.rand(int(mask.sum()), 1, generator=self.generator) * 0.4 - 0.2
        self.t[mask] = 0

    def _obs(self) -> dict[str, torch.Tensor]:
        return {"policy": self.pos.clone(), "critic": self.drift.clone()}

    def reset(self, seed: int | None = None) -> dict[str, torch.Tensor]:
        if seed is not None:
            self.generator.manual_seed(seed)
        self._new(torch.ones(self.num_envs, dtype=torch.bool))
        return self._obs()

    def step(self, actions: torch.Tensor) -> tuple[Any, torch.Tensor, torch.Tensor, dict[str, Any]]:
        self.pos = self.pos + self.drift + 0.1 * actions.clamp(-1, 1)
        self.t += 1
        reward, done = -self.pos.abs().squeeze(1), self.t >= 12
        if done.any():
            self._new(done)
        return self._obs(), reward, done, {}

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state(), "pos": self.pos.clone(), "drift": self.drift.clone(),
                "t": self.t.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.pos, self.drift, self.t = state["pos"].clone(), state["drift"].clone(), state["t"].clone()


def test_resume_with_groups_and_obs_norm_is_bit_for_bit(tmp_path: Any) -> None:
    def build() -> PPO:
        torch.manual_seed(1)
        env = DriftEnv()
        cfg = PPOConfig.cleanrl(rollout_steps=16, sgd_minibatch_size=16, num_sgd_iter=2, seed=1)  # obs, reward norm
        return PPO(env, MLPActorCritic.for_env(env), cfg)

    straight, resumed = learned_straight_and_resumed(build, DriftEnv, tmp_path / "groups.pt", epochs=2)
    for key in ("policy", "critic"):
        assert torch.equal(straight.obs_rms[key].var, resumed.obs_rms[key].var)
        assert torch.equal(straight.rollout.obs[key], resumed.rollout.obs[key])


def test_the_exported_actor_takes_the_policy_group_alone(tmp_path: Any) -> None:
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    env = cartpole()
    torch.manual_seed(0)
    ppo = PPO(env, MLPActorCritic.for_env(env), config(obs_norm=True))
    ppo.learn(1)
    session = ort.InferenceSession(ppo.export(tmp_path / "groups.onnx"))
    assert [i.name for i in session.get_inputs()] == ["policy"]
    obs = {"policy": torch.randn(16, 2), "critic": torch.randn(16, 2)}
    (actions,) = session.run(None, {"policy": obs["policy"].numpy()})
    np.testing.assert_array_equal(actions, ppo.act(obs, deterministic=True).numpy())


def test_noisy_entries_give_the_policy_noise_of_the_stated_size_and_the_critic_the_clean_state() -> None:
    """Truth: the wrapped CartPole's own observation (the critic's group, equal to an unwrapped env's of the same
    seed and actions) and the noise's sample moments over 4,000 steps against the stated σ per entry (a 99.9 %
    band for the mean and the standard deviation); the same seed gives the same noise; bad σ is refused."""
    from freeform.envs.partial import NoisyEntries

    std = np.array([0.1, 0.0, 0.02, 0.5], np.float32)
    env, plain = NoisyEntries(gym.make("CartPole-v1"), std, critic=True), gym.make("CartPole-v1")
    assert env.observation_space["policy"].shape == env.observation_space["critic"].shape == (4,)
    obs, _ = env.reset(seed=3)
    clean, _ = plain.reset(seed=3)
    noise, again = [], NoisyEntries(gym.make("CartPole-v1"), std, critic=True)
    first, _ = again.reset(seed=3)
    assert np.array_equal(first["policy"], obs["policy"])
    for t in range(4000):
        np.testing.assert_array_equal(obs["critic"], clean)
        noise.append(obs["policy"] - obs["critic"])
        action = t % 2
        obs, _, done, cut, _ = env.step(action)
        clean, _, _, _, _ = plain.step(action)
        if done or cut:
            obs, _ = env.reset(seed=t)
            clean, _ = plain.reset(seed=t)
    noise = np.array(noise, np.float64)
    n = len(noise)
    assert np.all(noise[:, 1] == 0.0)
    for i in (0, 2, 3):
        assert abs(noise[:, i].mean()) < 3.3 * std[i] / np.sqrt(n)
        assert abs(noise[:, i].std() / std[i] - 1.0) < 3.3 / np.sqrt(2 * n)
    alone = NoisyEntries(gym.make("CartPole-v1"), 0.1)
    assert alone.observation_space.shape == (4,) and alone.reset(seed=0)[0].shape == (4,)
    for bad in (-0.1, [0.1, 0.1], float("nan")):
        with pytest.raises(ValueError, match="std must be one finite number >= 0 or 4 of them"):
            NoisyEntries(gym.make("CartPole-v1"), bad)
