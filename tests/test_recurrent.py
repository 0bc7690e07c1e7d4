"""Recurrent policies: the hidden state resets at episode starts (terminations and time limits) and nowhere else,
a time limit's bootstrap value reads the state from before the reset, a sequence minibatch's loss equals the loss
recomputed step by step over the rollout, resume is bit for bit, the exported policy equals ``act()``, unsupported
combinations are refused, and an LSTM learns a task a feed-forward policy cannot."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch
import torch.nn as nn
from helpers import learned_straight_and_resumed

from freeform.agents import PPO, MLPActorCritic, PPOConfig, RecurrentActorCritic
from freeform.agents.ppo import ppo_loss, sequence_minibatch_loss
from freeform.agents.ppo.rollout import Sequences
from freeform.distributions import Categorical

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py


class CounterEnv:
    """N envs whose episodes last ``lengths[i]`` steps, ending alternately by termination and by a time limit
    (``info["truncated"]``, ``info["final_obs"]``). obs ``[N, 2]`` = (steps into the episode, env index); reward 1."""

    def __init__(self, lengths: tuple[int, ...] = (3, 5, 4, 7)) -> None:
        self.lengths = torch.tensor(lengths)
        self.num_envs, self.action_dim, self.device = len(lengths), 1, torch.device("cpu")
        self.observation_shape = (2,)
        self.t = torch.zeros(self.num_envs, dtype=torch.int64)
        self.episodes = torch.zeros(self.num_envs, dtype=torch.int64)

    def _obs(self) -> torch.Tensor:
        return torch.stack([self.t.float(), torch.arange(self.num_envs).float()], 1)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        self.t.zero_()
        self.episodes.zero_()
        return self._obs()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        self.t += 1
        done = self.t >= self.lengths
        info: dict[str, Any] = {}
        if done.any():
            info["truncated"] = done & (self.episodes % 2 == 1)  # every second episode ends at a time limit
            info["final_obs"] = self._obs()
            self.episodes += done.long()
            self.t[done] = 0
        return self._obs(), torch.ones(self.num_envs), done, info

    def state_dict(self) -> dict[str, Any]:
        return {"t": self.t.clone(), "episodes": self.episodes.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.t, self.episodes = state["t"].clone(), state["episodes"].clone()


class Counting(nn.Module):
    """A recurrent policy whose state counts the observations it has read in the episode: state' = state · (1 −
    start) + 1; V = the count after this step's observation (a Gaussian of mean 0 over one action)."""

    def __init__(self) -> None:
        super().__init__()
        self.log_std = nn.Parameter(torch.zeros(1))

    def initial_state(self, num_envs: int) -> tuple[torch.Tensor, ...]:
        return (torch.zeros(num_envs, 1),)

    def forward(self, obs: torch.Tensor, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor) -> tuple:
        (count,), values = state, []
        for t in range(obs.shape[0]):
            count = count * (~episode_start[t]).float()[:, None] + 1
            values.append(count[:, 0])
        value = torch.stack(values)
        mean = torch.zeros(*value.shape, 1)
        return mean, self.log_std.expand_as(mean), value, (count,)


def test_the_state_resets_at_episode_starts_and_nowhere_else() -> None:
    env = CounterEnv()
    ppo = PPO(env, Counting(), PPOConfig(rollout_steps=23, num_sgd_iter=1, sgd_minibatch_size=8, sequence_length=5))
    for _ in range(2):  # the second rollout starts from the first's carried state
        ppo.collect()
        buf = ppo.rollout
        steps_in = buf.obs[..., 0]  # the env's own count: observations before this one in the episode
        (stored,) = buf.states
        assert torch.equal(buf.episode_starts, steps_in == 0)  # reset exactly where an episode begins
        carried = stored[..., 0] * (~buf.episode_starts).float()  # the state the step reads, after the reset
        assert torch.equal(carried, steps_in)  # ... and carried everywhere else
        assert torch.equal(buf.values, steps_in + 1)
        truncated = buf.truncated
        assert truncated.any() and (buf.dones & ~truncated).any()
        # a time limit's bootstrap: V(final obs) from the state before the reset = the episode's length + 1
        lengths = env.lengths.expand_as(steps_in).float()
        assert torch.equal(buf.final_values[truncated], (lengths + 1)[truncated])


def small_recurrent(env: Any, rnn: str = "lstm") -> RecurrentActorCritic:
    torch.manual_seed(0)
    return RecurrentActorCritic.for_env(env, hidden=(8,), rnn=rnn, rnn_hidden=6)


@pytest.mark.parametrize("rnn", ["lstm", "gru"])
def test_a_sequence_minibatchs_loss_equals_the_loss_recomputed_step_by_step(rnn: str) -> None:
    env = CounterEnv()
    cfg = PPOConfig(rollout_steps=11, sequence_length=4, sgd_minibatch_size=8, num_sgd_iter=1, vf_clip_param=5.0,
                    value_clip="ppo2", entropy_coeff=0.01)  # 11 = 4 + 4 + 3: the last chunk padded
    ppo = PPO(env, small_recurrent(env, rnn), cfg)
    ppo.collect()
    buf, policy = ppo.rollout, ppo.policy
    # Independent truth: the policy one step at a time over the whole rollout from the first stored state.
    state, params, values = tuple(s[0] for s in buf.states), [], []
    with torch.no_grad():
        for t in range(11):
            *p, v, state = policy(buf.obs[t : t + 1], state, buf.episode_starts[t : t + 1])
            params.append(tuple(x[0] for x in p))
            values.append(v[0])
    assert torch.allclose(torch.stack(values), buf.values, atol=1e-6)  # the values the rollout stored
    batch = ppo._train_batch()
    seqs = ppo._sequences(batch)
    idx = torch.tensor([1, 6, 11])  # sequences: chunk c of env n is c·4 + n — (0, 1), (1, 2), (2, 3) the padded one
    kl = torch.tensor(0.2)
    with torch.no_grad():
        part = Sequences(seqs.obs[:, idx], tuple(s[idx] for s in seqs.state), seqs.starts[:, idx], seqs.mask[:, idx])
        loss, stats = sequence_minibatch_loss(
            policy, ppo.distribution, cfg, part, seqs.samples[:, idx].reshape(12, -1),
            seqs.advantages[:, idx].reshape(-1), kl)
        rows = [(t, n) for c, n in ((0, 1), (1, 2), (2, 3)) for t in range(4 * c, min(4 * c + 4, 11))]
        step_params = tuple(torch.stack([params[t][i][n] for t, n in rows]) for i in range(len(params[0])))
        step_values = torch.stack([values[t][n] for t, n in rows])
        flat = [t * 4 + n for t, n in rows]
        want_loss, want_stats = ppo_loss(step_params, step_values, ppo.distribution, cfg, batch.samples[flat],
                                         batch.advantages[flat], kl, torch.mean)
    assert len(rows) == 11 and int(seqs.mask[:, idx].sum()) == 11  # 4 + 4 + 3 real steps
    torch.testing.assert_close(loss, want_loss, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(stats, want_stats, rtol=1e-6, atol=1e-7)


def test_resume_with_a_recurrent_policy_is_bit_for_bit(tmp_path: Any) -> None:
    def build() -> PPO:
        env = CounterEnv()
        cfg = PPOConfig.cleanrl(rollout_steps=9, sequence_length=4, sgd_minibatch_size=8, num_sgd_iter=2, seed=3)
        return PPO(env, small_recurrent(env), cfg)

    straight, resumed = learned_straight_and_resumed(build, CounterEnv, tmp_path / "lstm.pt", epochs=3)
    for a, b in zip((*straight.policy_state, *straight.rollout.states), (*resumed.policy_state, *resumed.rollout.states),
                    strict=True):
        assert torch.equal(a, b)
    assert torch.equal(straight.episode_start, resumed.episode_start)
    assert torch.equal(straight.rollout.logprobs, resumed.rollout.logprobs)


def test_act_carries_the_state_and_the_export_equals_it(tmp_path: Any) -> None:
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    env = CounterEnv()
    ppo = PPO(env, small_recurrent(env), PPOConfig(rollout_steps=8, sgd_minibatch_size=8, num_sgd_iter=1,
                                                     obs_norm=True))
    ppo.learn(1)
    session = ort.InferenceSession(ppo.export(tmp_path / "lstm.onnx"))
    names = [i.name for i in session.get_inputs()]
    assert names == ["obs", "state_0", "state_1", "episode_start"]
    g = torch.Generator().manual_seed(0)
    state, onnx_state = None, [np.zeros((3, 1, 6), np.float32)] * 2
    for step in range(4):
        obs = torch.randn(3, 2, generator=g) * 4
        start = torch.tensor([step == 0, step == 2, False])
        actions, state = ppo.act(obs, state, start if step else None, deterministic=True)
        got, *onnx_state = session.run(None, {"obs": obs.numpy(), "state_0": onnx_state[0], "state_1": onnx_state[1],
                                              "episode_start": start.numpy()})
        np.testing.assert_allclose(got, actions.numpy(), rtol=1e-5, atol=1e-6)
        for a, b in zip(onnx_state, state[:2], strict=True):  # the actor's (h, c)
            np.testing.assert_allclose(a, b.numpy(), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="feed-forward"):
        PPO(CounterEnv(), MLPActorCritic(2, 1), PPOConfig(rollout_steps=4)).act(torch.zeros(4, 2), state)


def test_what_a_recurrent_policy_cannot_run_with_is_refused() -> None:
    env = CounterEnv()
    with pytest.raises(ValueError, match="cuda_graph"):
        PPO(env, small_recurrent(env), PPOConfig(rollout_steps=4, cuda_graph=True))
    with pytest.raises(ValueError, match="compile"):
        PPO(env, small_recurrent(env), PPOConfig(rollout_steps=4, compile=True))
    # (data-parallel runs split the sequences by env: tests/test_distributed.py, case "recurrent")


class CueEnv:
    """Remember a cue: the first observation shows a cue ±1, the next ``delay`` show 0; the last step's action (one of
    two) earns 1 if it names the cue. A feed-forward policy scores 0.5 at best, a recurrent one 1."""

    def __init__(self, num_envs: int = 16, delay: int = 2) -> None:
        self.num_envs, self.delay, self.device = num_envs, delay, torch.device("cpu")
        self.observation_shape, self.action_dim, self.action_distribution = (1,), 1, Categorical(2)
        self.generator = torch.Generator().manual_seed(0)
        self.t = 0

    def _new(self) -> torch.Tensor:
        self.cue = torch.randint(0, 2, (self.num_envs,), generator=self.generator)
        self.t = 0
        return (2.0 * self.cue - 1.0)[:, None]

    def reset(self, seed: int | None = None) -> torch.Tensor:
        if seed is not None:
            self.generator.manual_seed(seed)
        return self._new()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        self.t += 1
        if self.t <= self.delay:
            return torch.zeros(self.num_envs, 1), torch.zeros(self.num_envs), torch.zeros(self.num_envs, dtype=torch.bool), {}
        reward = (actions[:, 0] == self.cue).float()
        return self._new(), reward, torch.ones(self.num_envs, dtype=torch.bool), {}


def test_an_lstm_learns_to_remember_a_cue() -> None:
    env = CueEnv(num_envs=32)
    torch.manual_seed(0)
    policy = RecurrentActorCritic.for_env(env, hidden=(16,), rnn_hidden=16)
    cfg = PPOConfig(rollout_steps=12, sequence_length=6, sgd_minibatch_size=96, num_sgd_iter=4, lr=1e-2,
                    gae_lambda=0.95, kl_coeff=0.0, clip_param=0.2, entropy_coeff=0.01, seed=0)
    history = PPO(env, policy, cfg).learn(12)  # seeds 0-2: 0.98-1.0 after 8 epochs
    first, last = history[0]["episode_reward_mean"], np.mean([h["episode_reward_mean"] for h in history[-3:]])
    assert first < 0.7 and last > 0.9, (first, last)


def test_a_recurrent_policy_over_observation_groups_keeps_the_critics_group_from_its_actor() -> None:
    from test_observation_groups import DriftEnv  # (tests/ is on the path, as for helpers.py)

    env = DriftEnv()
    policy = small_recurrent(env)
    assert policy.actor_rnn.input_size == 1 and policy.critic_rnn.input_size == 2
    ppo = PPO(env, policy, PPOConfig(rollout_steps=6, sgd_minibatch_size=12, sequence_length=3, num_sgd_iter=1,
                                     obs_norm=True))
    ppo.learn(1)
    obs = {"policy": torch.randn(4, 1), "critic": torch.randn(4, 1)}
    other = {"policy": obs["policy"], "critic": obs["critic"] + 3.0}
    a, _ = ppo.act(obs, deterministic=True)
    b, _ = ppo.act(other, deterministic=True)
    assert torch.equal(a, b)
    with torch.no_grad():
        v = ppo.policy(ppo._here({k: x[None] for k, x in obs.items()}), ppo.policy.initial_state(4),
                       torch.ones(1, 4, dtype=torch.bool))[-2]
        w = ppo.policy({k: x[None] for k, x in other.items()}, ppo.policy.initial_state(4),
                       torch.ones(1, 4, dtype=torch.bool))[-2]
    assert not torch.equal(v, w)


@pytest.mark.parametrize("mode", ["next_step", "same_step"])
def test_gymnasium_autoreset_modes_reset_the_state_where_the_new_episode_begins(mode: str) -> None:
    """Through ``from_gymnasium``: with Gymnasium's next-step reset the step that only resets is no transition, and
    the state restarts at the new episode's first observation (the env's own time-in-episode, obs[0], is the count
    of observations the policy has read before it); with same-step reset, at the observation after the done."""
    pytest.importorskip("gymnasium")
    from gymnasium.vector import AutoresetMode
    from test_gymnasium import ToyVectorEnv

    from freeform.envs import from_gymnasium

    autoreset = AutoresetMode.NEXT_STEP if mode == "next_step" else AutoresetMode.SAME_STEP
    env = from_gymnasium(ToyVectorEnv([3, 0, 2], [0, 4, 0], autoreset))
    ppo = PPO(env, Counting(), PPOConfig(rollout_steps=13, num_sgd_iter=1, sgd_minibatch_size=8, sequence_length=4))
    for _ in range(2):
        ppo.collect()
        buf = ppo.rollout
        carried = buf.states[0][..., 0] * (~buf.episode_starts).float()
        real = buf.valid
        assert (~real).any() == (mode == "next_step")
        assert torch.equal(carried[real], buf.obs[..., 0][real])
        assert buf.truncated.any()
        ppo.update()
