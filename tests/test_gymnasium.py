"""Gymnasium both ways: ``from_gymnasium`` against hand-built toy vector envs (truncation vs termination, the
next-step autoreset, action clipping, normalisation statistics through a checkpoint, exact resume), ``to_gymnasium``
under Gymnasium's own env checker, and the ``cleanrl`` preset solving MuJoCo's InvertedPendulum."""

from __future__ import annotations

import math
import time
import warnings
from typing import Any

import numpy as np
import pytest
import torch
import torch.nn as nn

gym = pytest.importorskip("gymnasium")
from gymnasium.vector import AutoresetMode  # noqa: E402
from helpers import SingleView  # noqa: E402  (tests/helpers.py)

from freeform.agents import PPO, MLPActorCritic, PPOConfig  # noqa: E402
from freeform.agents.ppo import CLEANRL_PRESET, compute_advantages  # noqa: E402
from freeform.envs import DesignEnv, EnvConfig, VecEnv, VolumeTask, from_gymnasium, to_gymnasium  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py

GAMMA = 0.99


class ToyVectorEnv(gym.vector.VectorEnv):
    """N counters, hand-built: obs = (time in episode, env index, 1 on an episode's last observation) float32 [N, 3];
    action Box(−½, ½, (1,)); reward = 1 + t/10 each step; env i terminates after ``terminate_at[i]`` steps or is
    truncated by a time limit after ``truncate_at[i]`` (whichever comes first; 0 = never). Records the actions it
    was given. Any autoreset mode; ``state_dict`` for exact resume."""

    def __init__(self, terminate_at: list[int], truncate_at: list[int], mode: AutoresetMode = AutoresetMode.NEXT_STEP):
        self.num_envs = len(terminate_at)
        self.metadata = {"autoreset_mode": mode}
        self.terminate_at, self.truncate_at = np.array(terminate_at), np.array(truncate_at)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
        self.single_action_space = gym.spaces.Box(-0.5, 0.5, (1,), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.t = np.zeros(self.num_envs, dtype=np.int64)
        self.pending = np.zeros(self.num_envs, dtype=bool)
        self.received: list[np.ndarray] = []

    def _obs(self, last: np.ndarray | None = None) -> np.ndarray:
        last = np.zeros(self.num_envs) if last is None else last
        return np.stack([self.t, np.arange(self.num_envs), last], axis=1).astype(np.float32)

    def reset(self, *, seed: Any = None, options: dict | None = None):  # type: ignore[override]
        mask = (options or {}).get("reset_mask", np.ones(self.num_envs, dtype=bool))
        self.t[mask] = 0
        self.pending[mask] = False
        return self._obs(), {}

    def step(self, actions: np.ndarray):  # type: ignore[override]
        self.received.append(np.array(actions, copy=True))
        resetting = self.pending.copy()
        self.t[resetting] = 0
        stepping = ~resetting
        self.t[stepping] += 1
        reward = np.where(stepping, 1.0 + self.t / 10.0, 0.0)
        terminated = stepping & (self.terminate_at > 0) & (self.t >= self.terminate_at)
        truncated = stepping & ~terminated & (self.truncate_at > 0) & (self.t >= self.truncate_at)
        done = terminated | truncated
        obs = self._obs(done.astype(float))
        info: dict[str, Any] = {}
        mode = self.metadata["autoreset_mode"]
        if mode == AutoresetMode.NEXT_STEP:
            self.pending = done
        elif mode == AutoresetMode.SAME_STEP and done.any():
            info["final_obs"] = np.array([obs[i] if done[i] else None for i in range(self.num_envs)], dtype=object)
            info["_final_obs"] = done.copy()
            self.t[done] = 0
            obs = self._obs()
        return obs, reward, terminated, truncated, info

    def state_dict(self) -> dict[str, Any]:
        return {"per_env": {"t": torch.as_tensor(self.t.copy()), "pending": torch.as_tensor(self.pending.copy())}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.t = state["per_env"]["t"].numpy().copy()
        self.pending = state["per_env"]["pending"].numpy().copy()


def toy_ppo(mode: AutoresetMode, terminate_at=(3, 0), truncate_at=(0, 4), **cfg: Any) -> PPO:
    torch.manual_seed(0)
    env = from_gymnasium(ToyVectorEnv(list(terminate_at), list(truncate_at), mode))
    config = dict(rollout_steps=8, num_sgd_iter=2, sgd_minibatch_size=4, lr=1e-3, gae_lambda=1.0, seed=1)
    return PPO(env, MLPActorCritic(3, 1, hidden=(8,)), PPOConfig(**{**config, **cfg}))


def test_adapter_follows_the_vecenv_protocol() -> None:
    env = from_gymnasium(ToyVectorEnv([3, 0], [0, 4]))
    assert isinstance(env, VecEnv) and env.num_envs == 2 and env.observation_shape == (3,) and env.action_dim == 1
    obs = env.reset(seed=0)
    assert obs.dtype == torch.float32 and obs.shape == (2, 3)
    with pytest.raises(ValueError, match="cannot encode the Text space at observation"):
        from_gymnasium(gym.vector.SyncVectorEnv([TextEnv]))


class TextEnv(gym.Env):
    """Text observations: a space of no fixed size, which from_gymnasium refuses by name."""

    observation_space = gym.spaces.Text(8)
    action_space = gym.spaces.Discrete(2)

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):  # type: ignore[override]
        return "a", {}

    def step(self, action: Any):  # type: ignore[override]
        return "a", 0.0, True, False, {}


def test_truncation_bootstraps_and_termination_does_not_by_hand() -> None:
    """One env, T = 3, λ = 1: an episode truncated at t = 1 is bootstrapped with V(s_final) = 5, one terminated at
    t = 1 is not; the recursion stops at the done either way (the step after starts a new episode, cut at T with
    V(s_T) = 2)."""
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    dones = torch.tensor([[False], [True], [False]])
    values = torch.zeros(3, 1)
    last_value, final_values = torch.tensor([2.0]), torch.tensor([[0.0], [5.0], [0.0]])
    truncated = torch.tensor([[False], [True], [False]])
    _, ret_trunc = compute_advantages(rewards, values, dones, last_value, GAMMA, 1.0, truncated, final_values)
    _, ret_term = compute_advantages(rewards, values, dones, last_value, GAMMA, 1.0, torch.zeros_like(truncated), final_values)
    g = GAMMA
    torch.testing.assert_close(ret_trunc, torch.tensor([[1 + g * (2 + g * 5)], [2 + g * 5], [3 + g * 2]]))
    torch.testing.assert_close(ret_term, torch.tensor([[1 + g * 2], [2.0], [3 + g * 2]]))
    # No truncation at all: the paper's formula, bit for bit.
    a, r = compute_advantages(rewards, values, dones, last_value, GAMMA, 0.9)
    a2, r2 = compute_advantages(rewards, values, dones, last_value, GAMMA, 0.9, torch.zeros_like(truncated), final_values)
    assert torch.equal(a, a2) and torch.equal(r, r2)


def test_truncation_ends_the_episode_as_a_termination_when_bootstrap_truncated_is_off() -> None:
    """``bootstrap_truncated=False`` (CleanRL's scripts): env 1's truncated episode gets no V(s_final), its return
    at the last step is its reward, as env 0's terminated one; everything else in the rollout is unchanged."""
    on, off = toy_ppo(AutoresetMode.SAME_STEP), toy_ppo(AutoresetMode.SAME_STEP, bootstrap_truncated=False)
    on.collect()
    off.collect()
    assert on.rollout.truncated[3, 1] and not off.rollout.truncated.any()
    assert on.rollout.returns[3, 1] != on.rollout.rewards[3, 1]
    torch.testing.assert_close(off.rollout.returns[3, 1], off.rollout.rewards[3, 1])
    torch.testing.assert_close(off.rollout.returns[:, 0], on.rollout.returns[:, 0])  # env 0 terminated: the same
    assert torch.equal(off.rollout.actions, on.rollout.actions)


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_truncated_episode_bootstraps_in_the_loop(mode: AutoresetMode) -> None:
    """Env 0 terminates after 3 steps, env 1 is truncated after 4: the returns at the last step of each episode are
    r (terminated) and r + γ·V(s_final) (truncated), with V of the policy that collected the rollout; in every mode."""
    ppo = toy_ppo(mode)
    ppo.collect()
    ro = ppo.rollout
    final_obs = torch.tensor([[4.0, 1.0, 1.0]])  # env 1's last observation: t = 4, index 1, last = 1
    v_final = ppo.policy(final_obs)[2][0]
    assert ro.dones[2, 0] and not ro.truncated[2, 0]  # env 0: terminated at its 3rd step
    torch.testing.assert_close(ro.returns[2, 0], ro.rewards[2, 0])
    assert ro.dones[3, 1] and ro.truncated[3, 1]  # env 1: truncated at its 4th step
    torch.testing.assert_close(ro.final_values[3, 1], v_final)
    torch.testing.assert_close(ro.returns[3, 1], ro.rewards[3, 1] + GAMMA * v_final)
    torch.testing.assert_close(ro.returns[2, 1], ro.rewards[2, 1] + GAMMA * ro.returns[3, 1])
    # env 1 is truncated again at index 7, or at 8 (outside the rollout) after the next-step mode's reset step
    assert ro.truncated.sum() == (1 if mode == AutoresetMode.NEXT_STEP else 2)
    # Episodes as the design env reports them: raw returns and lengths of env 0's terminated episode.
    assert float(ro.rewards[0:3, 0].sum()) == pytest.approx(1.1 + 1.2 + 1.3)


def test_next_step_autoreset_step_never_reaches_the_loss() -> None:
    """Gymnasium's default mode: the step after an episode's end only resets the env. Those samples are marked
    invalid, excluded from the minibatches (the policy never sees a last observation in the update), from the batch
    standardisation and from the episode lengths."""
    ppo = toy_ppo(AutoresetMode.NEXT_STEP, rollout_steps=10, sgd_minibatch_size=3, num_sgd_iter=3)
    seen: list[torch.Tensor] = []
    forward = ppo.policy.forward

    def spy(obs: torch.Tensor):
        if ppo.policy.training:
            seen.append(obs.clone())
        return forward(obs)

    ppo.policy.forward = spy  # type: ignore[method-assign]
    stats = ppo.train_epoch()
    ro = ppo.rollout
    # env 0: episodes at indices 0-2 and 4-6, reset steps at 3 and 7; env 1: episodes at 0-3 and 5-8, resets at 4, 9.
    expected_invalid = {(3, 0), (7, 0), (4, 1), (9, 1)}
    invalid = {(int(t), int(n)) for t, n in (~ro.valid).nonzero().tolist()}
    assert invalid == expected_invalid
    assert all(ro.obs[t, n, 2] == 1.0 for t, n in invalid)  # they hold the last observation of an episode
    seen_obs = torch.cat(seen)
    assert (seen_obs[:, 2] == 0.0).all()  # ... which the update never trained on
    assert len(seen_obs) == 3 * (int(ro.valid.sum()) // 3) * 3  # passes × minibatches of the 16 valid samples × 3
    assert stats["episodes"] == 4 and stats["episode_length_mean"] == pytest.approx((3 + 3 + 4 + 4) / 4)


def test_actions_are_clipped_for_the_env_and_stored_unclipped() -> None:
    ppo = toy_ppo(AutoresetMode.SAME_STEP)
    inner = ppo.env.vector_env
    ppo.collect()
    sent = torch.as_tensor(np.stack(inner.received)).reshape(8, 2, 1)
    stored = ppo.rollout.actions
    assert (stored.abs() > 0.5).any()  # σ = 1: many samples fall outside [−½, ½]
    torch.testing.assert_close(sent, stored.clamp(-0.5, 0.5))
    logprob = ppo.rollout.logprobs  # π_old's log-probability is that of the unclipped sample
    from freeform.agents.ppo import gaussian_log_prob

    torch.testing.assert_close(logprob, gaussian_log_prob(stored, ppo.rollout.means, ppo.rollout.log_stds))


@pytest.mark.parametrize("make", [
    lambda a: a, lambda a: a.double(), lambda a: a.t().contiguous().t(), lambda a: a.clone().requires_grad_(True),
    lambda a: a.to(torch.bfloat16),
], ids=["float32", "float64", "transposed", "requires_grad", "bfloat16"])
def test_the_env_gets_the_clipped_actions_whatever_the_tensor_and_the_tensor_is_untouched(make) -> None:
    """float32 CPU actions go to numpy directly (PPO's case), the others through a cast: the same clipped float32
    values reach the env, and the caller's tensor (PPO stores it) is never written."""
    inner = ToyVectorEnv([0, 0, 0], [0, 0, 0])
    env = from_gymnasium(inner)
    env.reset(seed=0)
    actions = make(torch.tensor([[-2.0], [0.25], [0.75]]))
    before = actions.detach().clone()
    env.step(actions)
    sent = inner.received[-1]
    assert sent.dtype == np.float32
    np.testing.assert_array_equal(sent, np.array([[-0.5], [0.25], [0.5]], dtype=np.float32))
    assert torch.equal(actions.detach(), before)


def test_running_statistics_match_gymnasiums_reference_for_single_samples_and_batches() -> None:
    """freeform's torch RunningMeanStd (in-place, a one-sample fast path) against Gymnasium's numpy original."""
    from gymnasium.wrappers.utils import RunningMeanStd as Reference

    from freeform.agents.ppo.normalization import RunningMeanStd

    rng = np.random.default_rng(0)
    ours, ref = RunningMeanStd((3,)), Reference(shape=(3,))
    for n in [1, 1, 5, 1, 2, 64, 1]:
        x = rng.normal([1.0, -2.0, 30.0], [0.5, 3.0, 0.01], size=(n, 3))
        ours.update(torch.from_numpy(x).float())
        ref.update(x.astype(np.float32).astype(np.float64))
        np.testing.assert_allclose(ours.mean.numpy(), ref.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ours.var.numpy(), ref.var, rtol=1e-12, atol=1e-15)
        assert ours.count == pytest.approx(ref.count, rel=1e-15)


def test_update_steps_is_one_update_per_step_of_gymnasiums_reference() -> None:
    """``update_steps`` (pooled prefix sums) = Gymnasium's RunningMeanStd updated batch by batch, after every batch."""
    from gymnasium.wrappers.utils import RunningMeanStd as Reference

    from freeform.agents.ppo.normalization import RunningMeanStd

    rng = np.random.default_rng(1)
    ours, ref = RunningMeanStd(()), Reference(shape=())
    ours.update(torch.tensor([3.0, -1.0]))
    ref.update(np.array([3.0, -1.0]))
    batches = rng.normal(50.0, 20.0, size=(300, 4))  # far from the prior mean: the sums must be well conditioned
    variances = ours.update_steps(torch.from_numpy(batches))
    for step, batch in enumerate(batches):
        ref.update(batch)
        assert variances[step].item() == pytest.approx(ref.var, rel=1e-10), step
    assert ours.mean.item() == pytest.approx(ref.mean, rel=1e-12) and ours.var.item() == pytest.approx(ref.var, rel=1e-10)
    assert ours.count == pytest.approx(ref.count, rel=1e-15)


def test_reward_scaling_is_gymnasiums_normalize_reward_step_by_step() -> None:
    """The rollout's scaled rewards = the per-step procedure of Gymnasium's NormalizeReward (each env's discounted
    return, its running variance updated every step, reward / √(var + 1e-8), reset at an episode's end), over two
    rollouts so that the carried returns and statistics count too. Raw rewards and dones are read off the env."""
    from gymnasium.wrappers.utils import RunningMeanStd as Reference

    ppo = toy_ppo(AutoresetMode.SAME_STEP, terminate_at=(3, 5), truncate_at=(0, 4), reward_norm=True)
    raw: list[tuple[np.ndarray, np.ndarray]] = []
    step = ppo.env.step

    def recording_step(actions: torch.Tensor):
        obs, reward, done, info = step(actions)
        raw.append((reward.numpy().astype(np.float64), done.numpy().copy()))
        return obs, reward, done, info

    ppo.env.step = recording_step  # type: ignore[method-assign]
    rms, returns, expected = Reference(shape=()), np.zeros(2), []
    for _ in range(2):
        ppo.collect()
        got = ppo.rollout.rewards.clone()
        for reward, done in raw:
            returns = returns * GAMMA + reward
            rms.update(returns)
            expected.append(np.clip(reward / np.sqrt(rms.var + 1e-8), -10, 10))
            returns[done] = 0.0
        unscaled = np.array([reward for reward, _ in raw])
        raw.clear()
        np.testing.assert_allclose(got.numpy(), np.array(expected[-8:]), rtol=1e-6)
        assert np.abs(got.numpy() - unscaled).max() > 0.1  # the scaling did act
    assert ppo.return_rms.var.item() == pytest.approx(rms.var, rel=1e-10)


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_episode_figures_match_gymnasiums_record_episode_statistics_across_rollouts(mode: AutoresetMode) -> None:
    """Episodes of 5 and 3 steps in rollouts of 8 (so episodes span rollouts, and in NEXT_STEP mode reset-only steps
    fall anywhere): PPO's episode returns and lengths, summed over each rollout after the loop and carried across
    rollouts, = what Gymnasium's own RecordEpisodeStatistics reports, every epoch."""
    torch.manual_seed(0)
    vec = gym.wrappers.vector.RecordEpisodeStatistics(ToyVectorEnv([5, 3], [0, 0], mode))
    ppo = PPO(from_gymnasium(vec), MLPActorCritic(3, 1, hidden=(8,)),
              PPOConfig(rollout_steps=8, num_sgd_iter=1, sgd_minibatch_size=4, seed=1))
    finished = 0
    for _ in range(4):
        stats = ppo.collect()
        returns, lengths = [], []
        for info in ppo.episode_infos:
            episode = info["gym_info"].get("episode")
            if episode is not None:
                ended = info["gym_info"]["_episode"]
                returns += list(episode["r"][ended])
                lengths += list(episode["l"][ended])
        assert stats["episodes"] == len(returns) > 0
        assert stats["episode_reward_mean"] == pytest.approx(np.mean(returns), rel=1e-6)
        assert (stats["episode_reward_min"], stats["episode_reward_max"]) == pytest.approx((min(returns), max(returns)))
        assert stats["episode_length_mean"] == pytest.approx(np.mean(lengths))
        finished += len(returns)
    assert finished >= 8


def test_episode_figures_are_absent_before_the_first_episode_and_never_nan_after() -> None:
    """Episodes of 5 steps in rollouts of 3: the first epoch finishes none (no figure, not NaN), the second one
    (its return), the third none (the latest finished ones': that one's, as SB3's episode buffer reports), and a
    checkpoint carries them."""
    torch.manual_seed(0)
    vec = gym.wrappers.vector.RecordEpisodeStatistics(ToyVectorEnv([5], [0], AutoresetMode.SAME_STEP))
    ppo = PPO(from_gymnasium(vec), MLPActorCritic(3, 1, hidden=(8,)),
              PPOConfig(rollout_steps=3, num_sgd_iter=1, sgd_minibatch_size=3, seed=1))
    first, second = ppo.collect(), ppo.collect()
    assert first["episodes"] == 0 and "episode_reward_mean" not in first and "episode_length_mean" not in first
    assert second["episodes"] == 1 and second["episode_length_mean"] == 5
    state = ppo.state_dict()
    third = ppo.collect()
    assert third["episodes"] == 0 and third["episode_reward_mean"] == second["episode_reward_mean"]
    ppo.recent_returns = torch.zeros(0)
    ppo.load_state_dict(state)
    assert ppo.recent_returns.tolist() == [pytest.approx(second["episode_reward_mean"])]


def test_critic_run_apart_trains_as_the_whole_network_run_each_step() -> None:
    """The same MLP behind a plain forward (PPO then runs actor and critic at every step, the general path) and
    with its halves (critic once per rollout): the same actions, log-probabilities, values and advantages over
    three epochs of training, up to float rounding (batched matrix products sum in another order)."""

    class Whole(nn.Module):  # forward only: no action_params/value, so PPO cannot split it
        def __init__(self, inner: MLPActorCritic) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            return self.inner(obs)

    runs = []
    for wrap in (False, True):
        torch.manual_seed(0)
        policy = MLPActorCritic(3, 1, hidden=(8,))
        env = from_gymnasium(ToyVectorEnv([3, 0], [0, 4], AutoresetMode.SAME_STEP))
        ppo = PPO(env, Whole(policy) if wrap else policy,
                  PPOConfig(rollout_steps=8, num_sgd_iter=2, sgd_minibatch_size=4, lr=1e-2, seed=1, obs_norm=True))
        assert ppo.critic_apart is not wrap
        epochs = []
        for _ in range(3):
            ppo.train_epoch()
            epochs.append({k: ppo.rollout[k].clone() for k in ("actions", "logprobs", "values", "advantages")})
        runs.append(epochs)
    for apart, whole in zip(*runs, strict=True):
        for key in apart:
            torch.testing.assert_close(apart[key], whole[key], rtol=1e-5, atol=1e-6)
    assert runs[0][2]["values"].std() > 0


def test_adapter_returns_new_tensors_even_when_the_vector_env_reuses_its_buffers() -> None:
    """``copy=False``: Gymnasium hands out the same observation array every step; PPO keeps a rollout's tensors, so
    the adapter must not alias it (the stored observations would all become the last one)."""
    vec = gym.vector.SyncVectorEnv([lambda: gym.make("Pendulum-v1")] * 2, copy=False)
    env = from_gymnasium(vec)
    first = env.reset(seed=0)
    second = env.step(torch.zeros(2, 1))[0]
    third = env.step(torch.ones(2, 1))[0]
    assert not torch.equal(first, second) and not torch.equal(second, third)
    assert first.data_ptr() != second.data_ptr() != third.data_ptr()


def _comparable(stats: dict[str, float]) -> dict[str, float]:
    return {k: v for k, v in stats.items() if not (k.startswith("time_") or k == "samples_per_second")}


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_normalisation_statistics_round_trip_and_resume_is_bit_exact(tmp_path: Any, mode: AutoresetMode) -> None:
    """obs_norm + reward_norm: the running statistics (tensors) and each env's discounted return go through the
    checkpoint; 2 epochs straight = 1 + save + load into fresh objects + 1, bit for bit."""
    kw = dict(obs_norm=True, reward_norm=True, advantage_norm="minibatch", gae_lambda=0.95)
    straight = toy_ppo(mode, **kw)
    s = [straight.train_epoch(), straight.train_epoch()]
    first = toy_ppo(mode, **kw)
    r1 = first.train_epoch()
    first.save(tmp_path / "norm.pt")
    state = torch.load(tmp_path / "norm.pt", weights_only=True)["ppo"]
    assert set(state["obs_rms"]) == {"mean", "var", "count"} and state["obs_rms"]["mean"].dtype == torch.float64
    assert "discounted_return" in state["per_env"]
    resumed = PPO.load(tmp_path / "norm.pt", from_gymnasium(ToyVectorEnv([3, 0], [0, 4], mode)))
    for rms in ("obs_rms", "return_rms"):
        for name, value in getattr(first, rms).state_dict().items():
            assert torch.equal(getattr(resumed, rms).state_dict()[name], value), (rms, name)
    r2 = resumed.train_epoch()
    assert _comparable(s[0]) == _comparable(r1)
    assert _comparable(s[1]) == _comparable(r2)
    for a, b in zip(straight.policy.parameters(), resumed.policy.parameters(), strict=True):
        assert torch.equal(a, b)
    for name in ("obs", "actions", "rewards", "returns", "valid", "truncated"):
        assert torch.equal(straight.rollout[name], resumed.rollout[name]), name
    # act() applies the saved statistics: the same raw observation gives the same action in both.
    raw = torch.tensor([[2.0, 1.0, 0.0]])
    assert torch.equal(straight.act(raw, deterministic=True), resumed.act(raw, deterministic=True))
    assert not torch.equal(straight.act(raw, deterministic=True), straight.policy(raw)[0])  # normalised first


def test_evaluation_runs_deterministic_episodes_on_its_own_env() -> None:
    ppo = toy_ppo(AutoresetMode.NEXT_STEP, eval_every=2, eval_episodes=3)
    ppo.eval_env = from_gymnasium(ToyVectorEnv([2, 5], [0, 0]))
    generator = ppo.generator.get_state()
    result = ppo.evaluate()
    assert torch.equal(generator, ppo.generator.get_state())  # no draw from the training stream
    # env 0 runs 2 episodes of 2 steps (1.1 + 1.2), env 1 one of 5 steps (1.1 + … + 1.5)
    assert result["eval_return"] == pytest.approx((2.3 + 2.3 + 6.5) / 3)
    assert result["eval_length_mean"] == pytest.approx(3.0)
    stats = [ppo.train_epoch() for _ in range(2)]
    assert "eval_return" not in stats[0] and stats[1]["eval_return"] == pytest.approx(result["eval_return"])


# ---------------------------------------------------------------------------------------------------------------
# The other direction.
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.filterwarnings("ignore:.*symmetric and normalized space")  # the design env's actions are in [−2, 2]
def test_to_gymnasium_design_env_passes_gymnasiums_checker() -> None:
    from gymnasium.utils.env_checker import check_env

    vec = to_gymnasium(DesignEnv(1, EnvConfig(resolution=4, steps=3),
                                 materials=2, task=VolumeTask(), compute_metrics=False))
    assert vec.single_observation_space == gym.spaces.Box(0, 1, (4, 4, 4), np.uint8)
    assert vec.single_action_space.shape == (5,) and vec.single_action_space.high[0] == 2.0
    check_env(SingleView(vec), skip_render_check=True)


def test_to_gymnasium_vector_semantics() -> None:
    env = DesignEnv(3, EnvConfig(resolution=4, steps=2), materials=2, task=VolumeTask(), compute_metrics=False)
    vec = to_gymnasium(env)
    assert vec.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (3, 4, 4, 4) and obs.dtype == np.uint8 and vec.observation_space.contains(obs)
    actions = vec.action_space.sample()
    obs, reward, term, trunc, info = vec.step(actions)
    assert not term.any() and not trunc.any() and (reward == 0).all()
    obs, reward, term, trunc, info = vec.step(actions)
    assert term.all() and not trunc.any() and (obs == 0).all()  # the next episode's empty grids
    assert info["_final_obs"].all() and all((f > 0).sum() == r for f, r in zip(info["final_obs"], reward, strict=True))
    # Gymnasium's own vector wrappers run on it.
    stats = gym.wrappers.vector.RecordEpisodeStatistics(to_gymnasium(env))
    stats.reset(seed=1)
    _, _, _, _, info = stats.step(actions)
    _, _, _, _, info = stats.step(actions)
    assert info["_episode"].all() and (info["episode"]["l"] == 2).all()


# ---------------------------------------------------------------------------------------------------------------
# The cleanrl preset on MuJoCo.
# ---------------------------------------------------------------------------------------------------------------


def test_cleanrl_preset_is_cleanrls_defaults() -> None:
    cfg = PPOConfig.cleanrl()
    assert (cfg.lr, cfg.adam_eps, cfg.gamma, cfg.gae_lambda, cfg.clip_param) == (3e-4, 1e-5, 0.99, 0.95, 0.2)
    assert (cfg.rollout_steps, cfg.sgd_minibatch_size, cfg.num_sgd_iter) == (2048, 64, 10)
    assert (cfg.value_clip, cfg.vf_clip_param, cfg.vf_loss_coeff, cfg.grad_clip) == ("ppo2", 0.2, 0.25, 0.5)
    assert (cfg.kl_coeff, cfg.entropy_coeff, cfg.advantage_norm, cfg.lr_schedule) == (0.0, 0.0, "minibatch", "linear")
    assert cfg.obs_norm and cfg.reward_norm and (cfg.obs_clip, cfg.reward_clip) == (10.0, 10.0)
    assert PPOConfig.cleanrl(rollout_steps=256).rollout_steps == 256
    defaults = PPOConfig()  # the paper's semantics stay the default: every switch off
    assert not defaults.obs_norm and not defaults.reward_norm and defaults.adam_eps == 1e-8 and defaults.eval_every == 0
    assert set(CLEANRL_PRESET) <= {f for f in PPOConfig.__dataclass_fields__}


@pytest.mark.parametrize("name", ["cleanrl", "cleanrl_discrete"])
def test_agent_cleanrl_on_the_command_line_is_the_preset(name: str) -> None:
    """``agent=cleanrl`` (``agent=cleanrl_discrete``) is built from PPOConfig.cleanrl()'s (``cleanrl_discrete()``'s)
    source (no YAML copy): equal to it in every field but the run-filled ones (rollout_steps = env.steps, seed =
    the run's, device = the trainer's)."""
    import dataclasses

    from freeform.config import compose, ppo_config

    cfg = compose("~experiment", f"agent={name}", "env.steps=7", "seed=3")  # (no preset over it)
    run, preset = ppo_config(cfg, device="cpu"), getattr(PPOConfig, name)()
    for field in dataclasses.fields(PPOConfig):
        if field.name not in ("rollout_steps", "seed", "device"):
            assert getattr(run, field.name) == getattr(preset, field.name), field.name
    assert (run.rollout_steps, run.seed) == (7, 3)
    assert compose("~experiment", f"agent={name}", "agent.lr=0.01").agent.lr == 0.01  # overridable field by field
    assert (preset.entropy_coeff, preset.num_sgd_iter) == ((0.01, 4) if name == "cleanrl_discrete" else (0.0, 10))


@pytest.mark.slow
def test_cleanrl_preset_solves_inverted_pendulum() -> None:
    """CleanRL's defaults (batch 2048 = 8 envs × 256 steps, 32 minibatches, 10 passes, lr annealed over 100k steps)
    reach a deterministic evaluation return ≥ 950 (the maximum is 1000) within 100k steps, in under a minute."""
    pytest.importorskip("mujoco")

    def make() -> Any:
        return gym.make_vec("InvertedPendulum-v5", num_envs=8, vectorization_mode="sync",
                            vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})

    budget, batch = 100_000, 2048
    torch.manual_seed(1)
    cfg = PPOConfig.cleanrl(rollout_steps=batch // 8, lr_anneal_epochs=budget // batch, eval_every=2, eval_episodes=8)
    ppo = PPO(from_gymnasium(make()), MLPActorCritic(4, 1), cfg, eval_env=from_gymnasium(make()))
    start, best = time.perf_counter(), -math.inf
    while ppo.global_step < budget and best < 950:
        stats = ppo.train_epoch()
        best = max(best, stats.get("eval_return", -math.inf))
    elapsed = time.perf_counter() - start
    assert best >= 950, (best, ppo.global_step)
    assert elapsed < 60, elapsed


def test_bench_gym_results_accumulate_across_invocations_and_a_rerun_replaces_its_row(tmp_path, monkeypatch, capsys):
    """The 12-run MuJoCo table runs for hours, possibly in parts: every run lands in results.json at once, a second
    invocation (other frameworks) adds to it, a rerun of the same framework/task/seed/steps replaces its row."""
    import json

    from benchmarks import bench_gym

    walls = iter([100.0, 200.0, 300.0, 50.0])

    def fake_run(fw, task, steps, seed, script, workdir):
        return {"framework": fw, "task": task, "seed": seed, "steps": steps, "final_return": 1.0, "episodes": 3,
                "wall_s": next(walls)}

    monkeypatch.setattr(bench_gym, "one_run", fake_run)
    common = ["--tasks", "Hopper-v5", "--steps", "4096", "--seeds", "0", "--workdir", str(tmp_path)]
    bench_gym.run([*common, "--frameworks", "sb3", "cleanrl"])
    assert len(json.loads((tmp_path / "results.json").read_text())) == 2
    bench_gym.run([*common, "--frameworks", "freeform"])
    bench_gym.run([*common, "--frameworks", "freeform"])  # rerun: replaces the 300 s row with 50 s
    rows = json.loads((tmp_path / "results.json").read_text())
    assert sorted((r["framework"], r["wall_s"]) for r in rows) == [("cleanrl", 200.0), ("freeform", 50.0),
                                                                     ("sb3", 100.0)]
    capsys.readouterr()
    shown = bench_gym.run([*common, "--show"])
    assert [r["framework"] for r in shown] == ["freeform", "sb3", "cleanrl"]
    table = capsys.readouterr().out
    assert "| Hopper-v5 | sb3 | 1.0 | 1.0 | 100 | 100 | 2.00 |" in table  # 100 s against freeform's 50 s


def test_resuming_an_env_that_cannot_save_its_state_warns() -> None:
    """Gymnasium's own vector envs have no state_dict: a resume says that they start afresh (README)."""
    env = from_gymnasium(gym.vector.SyncVectorEnv([lambda: gym.make("Pendulum-v1")]), seed=0)
    state = env.state_dict()
    assert "vector_env" not in state
    with pytest.warns(RuntimeWarning, match="cannot save its state.*fresh reset"):
        env.load_state_dict(state)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from_gymnasium(ToyVectorEnv([3, 0], [0, 4]), seed=0).load_state_dict(
            from_gymnasium(ToyVectorEnv([3, 0], [0, 4]), seed=0).state_dict())
