"""Rollout collection: PPO's acting step and ``collect`` (``_step_envs`` → ``_complete_rollout`` →
``_episode_figures`` → ``_learning_targets``), as a part of the ``PPO`` class (``ppo.py``).

Shapes: ``T`` = ``rollout_steps``, ``N`` = ``env.num_envs`` (this rank's), ``A`` = ``env.action_dim``.
"""

from __future__ import annotations

import time
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.distributed import Collectives
from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.losses import compute_advantages, discounted_cumsum, leave_one_out
from freeform.agents.ppo.normalization import RunningMeanStd
from freeform.agents.ppo.rollout import Observation, Rollout, obs_first, obs_map
from freeform.distributions import ActionDistribution
from freeform.envs.base import VecEnv


class RolloutCollection:
    """The rollout half of :class:`freeform.agents.PPO`: what it reads and writes of the PPO is declared here."""

    config: PPOConfig
    env: VecEnv
    policy: nn.Module
    distribution: ActionDistribution
    dp: Collectives
    device: torch.device
    generator: torch.Generator
    critic_apart: bool
    recurrent: bool
    policy_state: tuple[torch.Tensor, ...]
    episode_start: torch.Tensor
    num_envs: int
    global_step: int
    obs: Observation
    rollout: Rollout
    episode_infos: list[dict[str, Any]]
    episode_return: torch.Tensor
    episode_length: torch.Tensor
    recent_returns: torch.Tensor
    recent_lengths: torch.Tensor
    obs_rms: RunningMeanStd | dict[str, RunningMeanStd] | None
    return_rms: RunningMeanStd | None
    discounted_return: torch.Tensor

    # -- acting ----------------------------------------------------------------------------------------------------

    def _sample(
        self, obs: torch.Tensor, deterministic: bool = False, noise: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None, tuple[torch.Tensor, ...]]:
        """obs ``[N, ...]`` → (action ``[N, A]``, value ``[N]``, the distribution's parameters); ``noise [N, A]`` of
        the distribution's ``noise_kind``, else drawn from ``self.generator``. ``value`` is None when the critic runs
        apart (``critic_apart``)."""
        if self.critic_apart:
            params, value = tuple(self.policy.action_params(obs)), None
        else:
            *params, value = self.policy(obs)
            params = tuple(params)
        if deterministic:
            return self.distribution.mode(params), value, params
        if noise is None:
            noise = self.dp.env_noise(params[0].new_empty(params[0].shape[0], self.env.action_dim), self.generator,
                                      self.distribution.noise_kind)
        return self.distribution.sample(params, noise), value, params

    def _sample_recurrent(
        self, obs: Observation, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor,
        deterministic: bool = False, noise: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        """:meth:`_sample` for a recurrent policy: obs ``[N, ...]``, its ``state`` before this step and
        ``episode_start [N]`` (reset there first) → (action, value ``[N]``, parameters, the state after the step)."""
        *params, value, state = self.policy(obs_map(lambda x: x[None], obs), state, episode_start[None])
        params = tuple(p[0] for p in params)
        if deterministic:
            return self.distribution.mode(params), value[0], params, state
        if noise is None:
            noise = self.dp.env_noise(params[0].new_empty(params[0].shape[0], self.env.action_dim), self.generator,
                                      self.distribution.noise_kind)
        return self.distribution.sample(params, noise), value[0], params, state

    def _recurrent_value(self, obs: Observation, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
                         ) -> torch.Tensor:
        """V(obs) ``[N]`` of a recurrent policy from ``state`` (its state is not advanced)."""
        return self.policy(obs_map(lambda x: x[None], obs), state, episode_start[None])[-2][0]

    def _here(self, obs: Observation) -> Observation:
        """``obs`` on the PPO device (no operation where it is there already)."""
        return obs_map(lambda x: x if x.device == self.device else x.to(self.device), obs)

    def _value(self, obs: Observation) -> torch.Tensor:
        """V(obs) ``[N]`` for observations as the policy sees them."""
        return self.policy.value(obs) if self.critic_apart else self.policy(obs)[-1]

    def normalize_obs(self, obs: Observation) -> Observation:
        """What the policy sees: ``obs`` itself, or with ``obs_norm`` ``clip((obs − μ) / √(σ² + 1e-8), ±obs_clip)``
        (each part of a dict observation by its own statistics: per group)."""
        rms, clip = self.obs_rms, self.config.obs_clip
        if rms is None:
            return obs
        if isinstance(rms, dict):
            return {k: rms[k].normalize(x, clip) for k, x in obs.items()}
        return rms.normalize(obs, clip)

    def _update_obs_rms(self, obs: Observation) -> None:
        """Fold observations into ``obs_norm``'s statistics: one set, or one per part of a dict observation."""
        rms = self.obs_rms
        if rms is None:
            return
        for stats, x in [(rms[k], obs[k]) for k in rms] if isinstance(rms, dict) else [(rms, obs)]:
            x, shape = self.dp.gather_envs(x), stats.mean.shape  # every rank's envs
            stats.update(x if x.shape[1:] == shape else x.reshape(-1, *shape))

    def _scale_rewards(self, rewards: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """``reward_norm``: the rollout's rewards ``[T, N]`` divided by √(Var[discounted return] + 1e-8), clipped.

        Step t reads the variance after the returns of steps ≤ t were folded in, as a per-step update would
        (Gymnasium's ``NormalizeReward``); each env's discounted return restarts where ``starts`` (its episode began)
        and carries over between rollouts in ``self.discounted_return``.
        """
        if self.return_rms is None:
            return rewards
        returns = discounted_cumsum(rewards.double(), self.config.gamma, starts, self.discounted_return)
        var = self.return_rms.update_steps(self.dp.gather_envs(returns, dim=1))  # every rank's envs, step by step
        self.discounted_return = returns[-1]
        scale = torch.rsqrt(var + 1e-8).to(rewards.dtype)
        return (rewards * scale[:, None]).clamp(-self.config.reward_clip, self.config.reward_clip)

    # -- rollout ---------------------------------------------------------------------------------------------------

    @torch.no_grad()
    def collect(self) -> dict[str, float]:
        """Step every env ``rollout_steps`` times with the current policy into ``self.rollout``; fill advantages."""
        self.policy.eval()
        time_env, scored, any_truncated = self._step_envs()
        starts = self._complete_rollout()
        returns, lengths = self._episode_figures(starts, scored)
        self._learning_targets(starts, any_truncated)
        self.global_step += self.config.rollout_steps * self.num_envs
        returns, lengths = self.dp.gather_varlen(returns), self.dp.gather_varlen(lengths)  # every rank's episodes
        stats = {"episodes": float(len(returns)), "time_env": time_env}
        returns, lengths = self._recent_episodes(returns, lengths)
        if len(returns):  # (absent until an episode has finished)
            stats.update(episode_reward_mean=returns.mean().item(), episode_reward_max=returns.max().item(),
                         episode_reward_min=returns.min().item(), episode_length_mean=lengths.float().mean().item())
        return stats

    def _recent_episodes(self, returns: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The episodes the statistics are over (``PPOConfig.stats_window``): this epoch's finished ones ``[E]``, or
        where it finished none the latest ``stats_window`` before it, which are kept for such an epoch (global:
        every rank's, the same on each)."""
        if len(returns):
            window = self.config.stats_window
            self.recent_returns = torch.cat([self.recent_returns, returns.detach().float().cpu()])[-window:]
            self.recent_lengths = torch.cat([self.recent_lengths, lengths.detach().long().cpu()])[-window:]
            return returns, lengths
        return self.recent_returns, self.recent_lengths

    def _step_envs(self) -> tuple[float, list[tuple[int, torch.Tensor]], bool]:
        """The rollout's one loop over time: act, step the envs, keep what each step gives; then stack the steps
        into the rollout. Returns the seconds spent in ``env.step``, the steps where the env reported its task's
        own score of the episodes ending there (``info["task_reward"]``), and whether any episode was truncated."""
        cfg, buf = self.config, self.rollout
        self.episode_infos = []
        time_env, any_truncated = 0.0, False
        buf.truncated.zero_()
        buf.final_values.zero_()
        buf.valid.fill_(True)
        # Each step's tensors are listed and stacked into the buffers once, after the loop; what needs no policy
        # (log-probabilities, reward scaling, episode sums) is computed there for the whole rollout. With one env
        # (a Gymnasium task) every tensor operation in this loop costs more than its arithmetic.
        seen, actions, values, rewards, dones = [], [], [], [], []
        params: list[tuple[torch.Tensor, ...]] = []
        scored: list[tuple[int, torch.Tensor]] = []
        # The whole rollout's noise in one draw, in the rollout's dtype (float32). On the CPU T draws of N·A values
        # equal one of T·N·A where N·A is a multiple of 16 (the design env's sizes); otherwise the stream differs.
        dist = self.distribution
        noise = self.dp.env_noise(buf.actions, self.generator, dist.noise_kind)
        # The env's tensors are moved or cast only where they need it: even a no-op .to() is an operation.
        env_device = self.env.device
        here = env_device is not None and torch.device(env_device) == self.device
        states, starts = [], []  # a recurrent policy's, before each step
        for t in range(cfg.rollout_steps):
            x = self.normalize_obs(self.obs)
            if self.recurrent:  # the state carried from the last step; reset where this observation starts an episode
                states.append(self.policy_state)
                starts.append(self.episode_start)
                action, value, step_params, self.policy_state = self._sample_recurrent(
                    x, self.policy_state, self.episode_start, noise=noise[t])
            else:
                action, value, step_params = self._sample(x, noise=noise[t])
            for store, item in ((seen, x), (actions, action), (values, value), (params, step_params)):
                store.append(item)  # (values: None when the critic runs apart, after the loop)
            next_obs, reward, done, info, seconds = self._step_env(dist.env_actions(action), here)
            time_env += seconds
            rewards.append(reward)
            dones.append(done)
            if "autoreset" in info:  # the env only reset (Gymnasium's next-step autoreset): not a transition
                buf.valid[t] = ~info["autoreset"].to(self.device, torch.bool)
            if done.any():
                any_truncated |= self._episodes_ended(t, info, scored)
            self.obs = next_obs
            if self.recurrent:  # the next observation begins an episode (Gymnasium's next-step reset: the new one's)
                self.episode_start = done | buf.valid[t].logical_not() if "autoreset" in info else done
        self._stack_steps({"actions": actions, "rewards": rewards, "dones": dones, "obs": seen, "params": params,
                           "values": values, "states": states, "starts": starts})
        return time_env, scored, any_truncated

    def _step_env(self, to_env: torch.Tensor, here: bool
                  ) -> tuple[Observation, torch.Tensor, torch.Tensor, dict[str, Any], float]:
        """``env.step`` on the env's actions ``[N, A]`` (moved to the env's device unless ``here``): the next
        observation, reward ``[N]`` float32 and done ``[N]`` bool on PPO's device, the info, and the seconds the
        step took. The env's tensors are moved or cast only where they need it: even a no-op .to() is an operation."""
        t0 = time.perf_counter()
        next_obs, reward, done, info = self.env.step(to_env if here else to_env.to(self.env.device))
        seconds = time.perf_counter() - t0
        if not here or reward.dtype != torch.float32:
            reward = reward.to(self.device, torch.float32)
        if not here or done.dtype != torch.bool:
            done = done.to(self.device, torch.bool)
        if not here:
            next_obs = self._here(next_obs)
        if obs_first(next_obs).data_ptr() == obs_first(self.obs).data_ptr():
            raise ValueError("env.step returned the observation tensor of the previous step, written in place: a "
                             "VecEnv must return new tensors (PPO keeps every step's until the rollout ends)")
        self._update_obs_rms(next_obs)
        return next_obs, reward, done, info, seconds

    def _episodes_ended(self, t: int, info: dict[str, Any], scored: list[tuple[int, torch.Tensor]]) -> bool:
        """Step ``t`` ended episodes: keep its ``info``, its task score (``scored``) and, for a time limit, the
        bootstrap value V(last observation) in ``final_values``. Returns whether any episode was truncated."""
        self.episode_infos.append(info)
        if "task_reward" in info:  # shaped rewards (dense_every): the return is what the task scored
            scored.append((t, info["task_reward"]))
        if "truncated" not in info or not self.config.bootstrap_truncated:
            return False
        truncated = info["truncated"].to(self.device, torch.bool)
        if not truncated.any():
            return False
        buf = self.rollout
        buf.truncated[t] = truncated
        final = self.normalize_obs(self._here(info["final_obs"]))
        final_value = (self._recurrent_value(final, self.policy_state, torch.zeros_like(truncated))
                       if self.recurrent else self._value(final))  # the state before the reset
        buf.final_values[t] = torch.where(truncated, final_value, 0.0)
        return True

    def _stack_steps(self, steps: dict[str, list[Any]]) -> None:
        """Each step's tensors (lists over the rollout's T steps, by column) stacked into the rollout's buffers."""
        buf = self.rollout
        for name in ("actions", "rewards", "dones"):
            torch.stack(steps[name], out=buf[name])
        if isinstance(buf.obs, torch.Tensor):
            torch.stack(steps["obs"], out=buf.obs)
        else:
            for key, stored in buf.obs.items():
                torch.stack([x[key] for x in steps["obs"]], out=stored)
        for i, stored in enumerate(buf.params):
            torch.stack([p[i] for p in steps["params"]], out=stored)
        if not self.critic_apart:
            torch.stack(steps["values"], out=buf.values)
        for i, stored in enumerate(buf.states):
            torch.stack([s[i] for s in steps["states"]], out=stored)
        if steps["starts"]:
            torch.stack(steps["starts"], out=buf.episode_starts)

    def _complete_rollout(self) -> torch.Tensor:
        """What the rollout needs no per-step policy for, at once: the critic's values (when it runs apart) and the
        log-probabilities. Returns ``starts [T, N]``: where an episode began (after a done)."""
        buf = self.rollout
        if self.critic_apart:
            buf.values = self._value(obs_map(lambda x: x.reshape(-1, *x.shape[2:]), buf.obs)).reshape(buf.values.shape)
        buf.logprobs = self.distribution.log_prob(buf.params, buf.actions)
        return torch.cat([torch.zeros_like(buf.dones[:1]), buf.dones[:-1]])

    def _episode_figures(self, starts: torch.Tensor, scored: list[tuple[int, torch.Tensor]]
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each episode's raw return and length, computed here only (``rollout.episode_returns``: TensorBoard, the
        console and the design records all read it): sums of the raw rewards carried across rollouts, or the task's
        own score where the env reported one. Returns the finished episodes' returns and lengths (this rank's)."""
        buf = self.rollout
        episode_returns = discounted_cumsum(buf.rewards, 1.0, starts, self.episode_return)
        for t, score in scored:
            episode_returns[t] = torch.where(buf.dones[t], score.to(self.device, torch.float32), episode_returns[t])
        buf.episode_returns = episode_returns
        episode_lengths = discounted_cumsum(buf.valid.float(), 1.0, starts, self.episode_length)  # exact < 2²⁴
        returns, lengths = episode_returns[buf.dones], episode_lengths[buf.dones].round().long()
        last_done = buf.dones[-1]
        self.episode_return = torch.where(last_done, 0.0, episode_returns[-1]).to(self.episode_return.dtype)
        self.episode_length = torch.where(last_done, 0.0, episode_lengths[-1]).round().to(self.episode_length.dtype)
        return returns, lengths

    def _learning_targets(self, starts: torch.Tensor, any_truncated: bool) -> None:
        """The rewards PPO learns from (scaled with ``reward_norm``) and GAE's advantages and value targets; an
        episode that the rollout cut is bootstrapped with V of its last observation."""
        cfg, buf = self.config, self.rollout
        if cfg.group_baseline:
            buf.rewards = leave_one_out(buf.rewards, self.reward_groups)
        buf.rewards = self._scale_rewards(buf.rewards, starts)
        if self.return_rms is not None:
            self.discounted_return = torch.where(buf.dones[-1], 0.0, self.discounted_return)
        seen = self.normalize_obs(self.obs)
        buf.last_value = (self._recurrent_value(seen, self.policy_state, self.episode_start) if self.recurrent
                          else self._value(seen))
        buf.advantages, buf.returns = compute_advantages(
            buf.rewards, buf.values, buf.dones, buf.last_value, cfg.gamma, cfg.gae_lambda,
            *((buf.truncated, buf.final_values) if any_truncated else ()),
        )


__all__ = ["RolloutCollection"]
