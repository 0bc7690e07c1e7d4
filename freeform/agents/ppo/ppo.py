"""Batched PPO, written out top to bottom: rollout → returns/advantages → loss → update → KL schedule.

The default configuration reproduces the semantics of RLlib 2.0.1's PPO as the paper used it (spec ``ppo.md``):
GAE with λ = 1 (advantage = discounted return − V), advantages standardised once over the whole train batch, the
clipped surrogate, the squared value error clamped at ``vf_clip_param``, a KL(π_old ‖ π) penalty whose coefficient
adapts after every epoch, Adam without gradient clipping. Common variants are switches in ``PPOConfig``.

Shapes: ``T`` = ``rollout_steps``, ``N`` = ``env.num_envs``, ``A`` = ``env.action_dim``, ``B`` = ``T·N``.

The action distribution (``freeform.agents.distributions``: a Gaussian for Box actions, categoricals or bits for
discrete ones) is decided once, at construction, from the policy or the env (:func:`choose_distribution`); below,
``self.distribution`` samples, scores and compares actions, and only the logged σ (a Gaussian's own figure) asks
which one it is.

Every collective sits behind ``self.dp`` (``freeform.agents.distributed.Collectives``), the identity in one process:
the code below is the single-process algorithm. Under ``torch.distributed`` (a process group of R > 1 ranks, e.g.
``torchrun``) each rank's env holds its slice of the environments, ``self.dp`` is a ``DataParallel`` and the update
uses the statistics of the global batch; the rules are in ``distributed.py`` (``docs/scaling.md``).
"""

from __future__ import annotations

import dataclasses
import os
import time
import types
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
import torch.nn as nn

from freeform.agents import distributed
from freeform.agents.distributed import PER_ENV
from freeform.agents.distributions import ActionDistribution, DiagGaussian, MaskedDiagGaussian
from freeform.agents.flat_params import FlatParameters
from freeform.agents.networks import DeclaresDistribution, GroupedActions, Rebuildable, SplitActorCritic
from freeform.agents.normalization import RunningMeanStd
from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.graphed import GraphedMinibatchStep
from freeform.agents.ppo.losses import (
    compute_advantages,
    discounted_cumsum,
    explained_variance,
    minibatch_loss,
    standardize,
    update_kl_coeff,
)
from freeform.agents.ppo.rollout import (
    Observation,
    Rollout,
    minibatch_samples,
    obs_first,
    obs_map,
    obs_shapes,
)
from freeform.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from freeform.envs.base import VecEnv
from freeform.learner import Episodes
from freeform.records import EpisodeCollector

if TYPE_CHECKING:  # (the TensorBoard writer is not imported with PPO)
    from freeform.logger import ScalarSink


class _TrainBatch(NamedTuple):
    """An update's view of the rollout: ``obs [B, ...]`` and ``samples [B, A + P + 3]`` (this rank's), ``advantages``
    of the global batch, ``kept`` (the global indices of real transitions, None: all) and the global sample count."""

    obs: Observation
    samples: torch.Tensor
    advantages: torch.Tensor
    kept: torch.Tensor | None
    size: int


def _own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with a code object of its own. torch.compile keeps its compiled graphs per code object, and each PPO's
    graph guards on its own policy, so PPO instances sharing ``minibatch_loss``'s code would recompile one another
    and, past ``torch._dynamo.config.recompile_limit`` (8) in one process (a sweep, a test suite), silently run
    eager; with its own code each instance compiles once."""
    copy = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__, copy.__doc__ = fn.__kwdefaults__, fn.__doc__
    return copy


class PPO:
    """Proximal policy optimisation over a batched environment (``freeform.envs.VecEnv``).

    After ``train_epoch()`` the caller may read ``rollout`` (the epoch's ``Rollout``) and ``episode_infos`` (the
    ``info`` dicts of the epoch's steps where any env finished an episode, in order). ``global_step`` counts env steps
    over all envs, ``epoch`` the epochs trained, ``kl_coeff`` is the current β.

    ``dp`` holds the collectives (``distributed.Collectives``; the identity in one process). Data-parallel when a
    process group of several ranks exists at construction: ``env`` is this rank's slice of the environments (slices
    contiguous in rank order), ``dp`` is a ``DataParallel``, ``num_envs`` is the global count;
    ``rollout``/``episode_infos`` stay local (``dp.gather_rollout`` gives the global view), statistics,
    ``global_step``, ``state_dict()`` and checkpoints are global. Every rank must call ``train_epoch``,
    ``state_dict``, ``save`` and ``load`` (collectives); only rank 0 writes the file.
    """

    def __init__(
        self,
        env: VecEnv,
        policy: nn.Module,
        config: PPOConfig | None = None,
        logger: ScalarSink | None = None,
        eval_env: VecEnv | None = None,
    ):
        self.config = config = config if config is not None else PPOConfig()
        if not isinstance(config, PPOConfig):
            raise ValueError(f"config must be a PPOConfig, got {type(config).__name__}")
        for attr in ("num_envs", "observation_shape", "action_dim", "reset", "step"):
            if not hasattr(env, attr):
                raise ValueError(f"env must follow freeform.envs.VecEnv; it has no {attr!r}")
        self.env = env
        self.device = torch.device(config.device) if config.device is not None else torch.device(env.device)
        self.policy = policy.to(self.device)
        self.logger = logger
        self.dp = distributed.collectives(env.num_envs, self.device)
        self.dp.broadcast_module_(self.policy)  # identical starting weights, whatever each rank's RNG did
        self.num_envs = self.dp.num_envs
        """N, environments over all ranks (= ``env.num_envs`` in one process)."""
        self.distribution = choose_distribution(policy, env)
        """The action distribution π(·|obs): the policy outputs its parameters (``param_dims``), then V."""
        if config.obs_norm and isinstance(self.distribution, MaskedDiagGaussian):
            raise ValueError("obs_norm would rescale the observation channel that the policy reads its action mask "
                             "from (a MaskedDiagGaussian's mask must stay 0/1): leave obs_norm off for a control env")
        self.critic_apart = isinstance(policy, SplitActorCritic)
        """The policy has ``action_params``/``value`` (actor and critic share nothing): the rollout runs the actor per
        step and the critic once over the rollout (``networks.py``)."""
        self.flat = FlatParameters(self.policy.parameters())
        """The policy's trainable parameters as views of one tensor (``flat.value``), gradients of another: Adam,
        clipping and zeroing are one operation each (``flat_params.py``)."""
        impl = {"fused": True} if config.fused_adam else {"foreach": True}
        if config.cuda_graph:
            if self.device.type != "cuda":
                raise ValueError(f"agent.cuda_graph needs a CUDA device, and this PPO runs on {self.device}: set "
                                 "agent.cuda_graph=false (the eager update is the CPU's)")
            if self.dp.world_size > 1:
                raise ValueError("agent.cuda_graph runs in one process only (a data-parallel rank's share of a "
                                 "minibatch varies in size, and a graph has fixed shapes): set agent.cuda_graph=false")
            impl["capturable"] = True  # the step count and the learning rate on the device: no sync in the graph
        self.optimizer = torch.optim.Adam([self.flat.value], lr=self._lr_value(config.lr), eps=config.adam_eps, **impl)
        self._minibatch_loss = torch.compile(_own_code(minibatch_loss), dynamic=False) if config.compile else minibatch_loss
        self._graphed = (GraphedMinibatchStep(self.policy, self.distribution, config, self.flat, self.optimizer,
                                              self._minibatch_mean, self.device) if config.cuda_graph else None)
        """The minibatch step as a CUDA graph (``agent.cuda_graph``), else None: the eager step in ``_sgd``."""
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.kl_coeff = float(config.kl_coeff)
        self.epoch = 0
        self.global_step = 0

        self.eval_env = eval_env
        """Where ``evaluate`` runs (every ``config.eval_every`` epochs); None = no evaluation."""
        self._eval_seeded = False
        # Running statistics of the optional normalisations (None when off, the paper's case).
        obs_shape = env.observation_shape
        if config.obs_norm and isinstance(obs_shape, Mapping):
            raise ValueError("obs_norm normalises one observation tensor, and this env observes a dict of them: "
                             "normalise inside the policy, or let the env flatten its observations")
        self.obs_rms = RunningMeanStd(tuple(obs_shape), self.device) if config.obs_norm else None
        self.return_rms = RunningMeanStd((), self.device) if config.reward_norm else None
        # float64 as the statistics (Gymnasium's too); only with reward_norm, as no float64 may exist (MPS)
        self.discounted_return = torch.zeros(env.num_envs, dtype=torch.float64 if config.reward_norm else torch.float32,
                                             device=self.device)
        """Each env's discounted return of raw rewards, whose running std scales the rewards (``reward_norm``)."""

        self.obs = self._here(env.reset(seed=config.seed))
        self._update_obs_rms(self.obs)
        self._check_policy()
        obs_dtype = torch.float32 if self.obs_rms is not None else None
        self.rollout = Rollout.allocate(config.rollout_steps, env.num_envs, self.obs, obs_dtype, env.action_dim,
                                        self.distribution.param_dims, self.device)
        self.episode_infos: list[dict[str, Any]] = []
        self._collector = EpisodeCollector()  # episodes() cuts the rollouts; its carry is part of the state
        self._collected = 0  # the epoch count at the last episodes() call
        # Running return and length of each env's current episode (they span epochs when episodes are cut).
        self.episode_return = torch.zeros(env.num_envs, dtype=torch.float32, device=self.device)
        self.episode_length = torch.zeros(env.num_envs, dtype=torch.int64, device=self.device)

    @torch.no_grad()
    def _check_policy(self) -> None:
        """Fail early, naming the mismatch, when the policy's outputs do not fit the env."""
        n, dist = self.env.num_envs, self.distribution
        try:
            outputs = self.policy(self.normalize_obs(self.obs))
        except Exception as e:
            raise ValueError(f"policy cannot read the env's observations {obs_shapes(self.obs)} ({e})") from e
        wanted = [(n, p) for p in dist.param_dims] + [(n,)]
        shapes = [tuple(x.shape) for x in outputs] if isinstance(outputs, tuple) else None
        if shapes != wanted:
            names = ", ".join(f"[{n}, {p}]" for p in dist.param_dims)
            raise ValueError(f"policy must return its {dist} parameters ({names}) and value [{n}] for this env, "
                             f"got {shapes if shapes is not None else type(outputs).__name__}")
        if self.critic_apart:  # the rollout calls the halves: they must be forward's
            seen = self.normalize_obs(self.obs)
            halves = (*self.policy.action_params(seen), self.policy.value(seen))
            if [tuple(x.shape) for x in halves] != shapes or not all(
                torch.allclose(h, o) for h, o in zip(halves, outputs, strict=True)
            ):
                raise ValueError("policy.action_params(obs) and policy.value(obs) must give what forward(obs) gives "
                                 f"(the distribution's parameters and the value, shapes {shapes})")

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

    def _here(self, obs: Observation) -> Observation:
        """``obs`` on the PPO device (no operation where it is there already)."""
        return obs_map(lambda x: x if x.device == self.device else x.to(self.device), obs)

    def _value(self, obs: Observation) -> torch.Tensor:
        """V(obs) ``[N]`` for observations as the policy sees them."""
        return self.policy.value(obs) if self.critic_apart else self.policy(obs)[-1]

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        """Actions ``[N, A]`` for raw observations ``[N, ...]`` (the distribution's mode if ``deterministic``: a
        Gaussian's mean), on the env's device, as the env takes them (int64 for a discrete distribution).

        With ``obs_norm`` the observations are normalised by the saved statistics (not updated). Sampling draws from
        the training generator, so calls between epochs shift the training's random stream.
        """
        x = self.normalize_obs(self._here(obs))
        return self.distribution.env_actions(self._sample(x, deterministic)[0]).to(self.env.device)

    def normalize_obs(self, obs: torch.Tensor) -> torch.Tensor:
        """What the policy sees: ``obs`` itself, or with ``obs_norm`` ``clip((obs − μ) / √(σ² + 1e-8), ±obs_clip)``."""
        if self.obs_rms is None:
            return obs
        return self.obs_rms.normalize(obs, self.config.obs_clip)

    def _update_obs_rms(self, obs: torch.Tensor) -> None:
        if self.obs_rms is not None:
            obs, shape = self.dp.gather_envs(obs), self.obs_rms.mean.shape  # every rank's envs
            self.obs_rms.update(obs if obs.shape[1:] == shape else obs.reshape(-1, *shape))

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
        nan = float("nan")
        return {
            "episode_reward_mean": returns.mean().item() if len(returns) else nan,
            "episode_reward_max": returns.max().item() if len(returns) else nan,
            "episode_reward_min": returns.min().item() if len(returns) else nan,
            "episode_length_mean": lengths.float().mean().item() if len(lengths) else nan,
            "episodes": float(len(returns)),
            "time_env": time_env,
        }

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
        for t in range(cfg.rollout_steps):
            x = self.normalize_obs(self.obs)
            action, value, step_params = self._sample(x, noise=noise[t])
            for store, item in ((seen, x), (actions, action), (values, value), (params, step_params)):
                store.append(item)  # (values: None when the critic runs apart, after the loop)
            to_env = dist.env_actions(action)  # (a Gaussian's: the same tensor)
            t0 = time.perf_counter()
            next_obs, reward, done, info = self.env.step(to_env if here else to_env.to(env_device))
            time_env += time.perf_counter() - t0
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
            rewards.append(reward)
            dones.append(done)
            if "autoreset" in info:  # the env only reset (Gymnasium's next-step autoreset): not a transition
                buf.valid[t] = ~info["autoreset"].to(self.device, torch.bool)
            if done.any():
                self.episode_infos.append(info)
                if "task_reward" in info:  # shaped rewards (dense_every): the return is what the task scored
                    scored.append((t, info["task_reward"]))
                if "truncated" in info and cfg.bootstrap_truncated:  # a time limit: bootstrap with V(last observation)
                    truncated = info["truncated"].to(self.device, torch.bool)
                    if truncated.any():
                        any_truncated = True
                        buf.truncated[t] = truncated
                        final_value = self._value(self.normalize_obs(self._here(info["final_obs"])))
                        buf.final_values[t] = torch.where(truncated, final_value, 0.0)
            self.obs = next_obs
        for name, steps in (("actions", actions), ("rewards", rewards), ("dones", dones)):
            torch.stack(steps, out=buf[name])
        if isinstance(buf.obs, torch.Tensor):
            torch.stack(seen, out=buf.obs)
        else:
            for key, stored in buf.obs.items():
                torch.stack([x[key] for x in seen], out=stored)
        for i, stored in enumerate(buf.params):
            torch.stack([p[i] for p in params], out=stored)
        if not self.critic_apart:
            torch.stack(values, out=buf.values)
        return time_env, scored, any_truncated

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
        buf.rewards = self._scale_rewards(buf.rewards, starts)
        if self.return_rms is not None:
            self.discounted_return = torch.where(buf.dones[-1], 0.0, self.discounted_return)
        buf.last_value = self._value(self.normalize_obs(self.obs))
        buf.advantages, buf.returns = compute_advantages(
            buf.rewards, buf.values, buf.dones, buf.last_value, cfg.gamma, cfg.gae_lambda,
            *((buf.truncated, buf.final_values) if any_truncated else ()),
        )

    # -- update ----------------------------------------------------------------------------------------------------

    def current_lr(self) -> float:
        """The learning rate of the coming epoch under ``config.lr_schedule``."""
        cfg = self.config
        if cfg.lr_schedule == "linear":
            return cfg.lr * max(0.0, 1.0 - self.epoch / cfg.lr_anneal_epochs)
        return cfg.lr

    def update(self) -> dict[str, float]:
        """``num_sgd_iter`` passes of minibatch SGD over ``self.rollout``, then the KL-coefficient update.

        Minibatches are drawn from the global batch (``B = T·N`` over all ranks). Data-parallel, every rank draws the
        same permutation, computes the samples of each minibatch it holds (``dp.local_share``) with loss *sums*
        divided by the global minibatch size (``dp.minibatch_mean``), and the gradients are summed over ranks
        (``dp.all_reduce_grad_``): the global minibatch's mean-loss gradient. In one process all three are plain.
        """
        cfg = self.config
        batch = self._train_batch()
        lr, kl_coeff = self.current_lr(), self.kl_coeff
        for group in self.optimizer.param_groups:
            if isinstance(group["lr"], torch.Tensor):  # a graph reads it: written in place
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr
        means = self._sgd(batch, kl_coeff)
        # RLlib's rule, on the mean KL over every minibatch update of the epoch (the same number on every rank).
        self.kl_coeff = update_kl_coeff(kl_coeff, means[2], cfg.kl_target)
        return self._update_stats(batch, means, kl_coeff, lr)

    def _train_batch(self) -> _TrainBatch:
        """The rollout flattened to this rank's ``B`` samples, and the global batch's advantages (standardised over
        the batch with ``advantage_norm="batch"``), on every rank: standardising over the batch or a minibatch is
        then the single process's formula on the same numbers."""
        buf, dp = self.rollout, self.dp
        size = buf.rewards.numel()  # this rank's samples
        obs = obs_map(lambda x: x.reshape(size, *x.shape[2:]), buf.obs)
        samples = minibatch_samples(buf.actions.reshape(size, -1), [p.reshape(size, -1) for p in buf.params],
                                    buf.logprobs.reshape(-1), buf.values.reshape(-1), buf.returns.reshape(-1))
        advantages = dp.gather_envs(buf.advantages, dim=1).reshape(-1)
        # Samples where an env only reset (Gymnasium's next-step autoreset) are no transitions: they are left out of
        # the minibatches and the batch statistics. ``kept`` = the global indices of the others (None: all of them).
        valid = dp.gather_envs(buf.valid, dim=1).reshape(-1)
        kept = None if bool(valid.all()) else valid.nonzero().squeeze(1)
        if self.config.advantage_norm == "batch":
            if kept is None:
                advantages = standardize(advantages)
            else:
                advantages = advantages.clone()
                advantages[kept] = standardize(advantages[kept])
        return _TrainBatch(obs, samples, advantages, kept, advantages.numel() if kept is None else kept.numel())

    def _sgd(self, batch: _TrainBatch, kl_coeff: float) -> list[float]:
        """``num_sgd_iter`` shuffled passes of minibatch Adam steps; the means over every minibatch of the policy
        loss, value loss, KL, entropy, clip fraction and total loss (over every rank)."""
        cfg, dp, flat = self.config, self.dp, self.flat
        minibatch = min(cfg.sgd_minibatch_size, batch.size)
        num_minibatches = batch.size // minibatch
        flat.check()

        def reduce(x: torch.Tensor) -> torch.Tensor:
            return dp.minibatch_mean(x, minibatch)

        kl_weight = torch.tensor(kl_coeff, device=self.device) if kl_coeff > 0.0 else None
        # Sums over minibatches, kept on the device so that no step waits for a host sync.
        # policy, value, kl, entropy, clip fraction, total loss
        totals = self._graphed.totals.zero_() if self._graphed is not None else torch.zeros(6, device=self.device)
        if self._graphed is not None:
            self._graphed.begin_update()
        self.policy.train()
        for _ in range(cfg.num_sgd_iter):
            order = torch.randperm(batch.size, generator=self.generator, device=self.device)
            if batch.kept is not None:
                order = batch.kept[order]
            for i in range(num_minibatches):
                idx = order[i * minibatch : (i + 1) * minibatch]
                adv = batch.advantages[idx]
                if cfg.advantage_norm == "minibatch":
                    adv = standardize(adv)
                if self._graphed is not None:  # the same step, replayed (one process: idx is the minibatch)
                    self._graphed(batch.obs, batch.samples, adv, idx, kl_weight)
                    continue
                idx, adv = dp.local_share(idx, adv)
                flat.zero_grad()
                if idx.numel():  # a rank may hold none of a minibatch; it then adds zero gradients
                    loss, stats = self._minibatch_loss(self.policy, self.distribution, cfg,
                                                       obs_map(lambda x, i=idx: x.index_select(0, i), batch.obs),
                                                       batch.samples.index_select(0, idx), adv, kl_weight, reduce)
                    loss.backward()
                    totals += stats
                dp.all_reduce_grad_(flat.grad)
                if cfg.grad_clip is not None:
                    flat.clip_grad_norm_(cfg.grad_clip)
                self.optimizer.step()
        dp.sum_(totals)  # each rank summed its shares of the minibatch means: their sum is the global mean
        return (totals / (cfg.num_sgd_iter * num_minibatches)).tolist()

    def _minibatch_mean(self, x: torch.Tensor) -> torch.Tensor:
        """The minibatch mean (``Collectives.minibatch_mean``) at the configured minibatch size: the graphed step's
        ``reduce`` (its minibatches are full ones of one process)."""
        return self.dp.minibatch_mean(x, x.shape[0])

    def _lr_value(self, lr: float) -> float | torch.Tensor:
        """The optimizer's lr as it holds it: a device tensor when a graph reads it (``cuda_graph``), else a float."""
        return torch.tensor(float(lr), device=self.device) if self.config.cuda_graph else lr

    def _update_stats(self, batch: _TrainBatch, means: list[float], kl_coeff: float, lr: float) -> dict[str, float]:
        """The update's statistics over the global batch (the values, returns and σ gathered from every rank)."""
        buf, dp, kept = self.rollout, self.dp, batch.kept
        values = dp.gather_envs(buf.values, dim=1).reshape(-1)
        returns = dp.gather_envs(buf.returns, dim=1).reshape(-1)
        if kept is not None:
            values, returns = values[kept], returns[kept]
        stats = {
            "policy_loss": means[0],
            "value_loss": means[1],
            "approx_kl": means[2],
            "entropy": means[3],
            "clip_fraction": means[4],
            "total_loss": means[5],
            "kl_coeff": kl_coeff,
            "lr": lr,
            "explained_variance": explained_variance(values, returns),
            "value_mean": values.mean().item(),
        }
        if isinstance(self.distribution, DiagGaussian):  # σ is the Gaussian's own figure (the others': entropy)
            stds = dp.gather_envs(buf.log_stds, dim=1).exp()
            if kept is not None:
                stds = stds.reshape(-1, stds.shape[-1])[kept]
            if isinstance(self.distribution, MaskedDiagGaussian):  # over the entries that act
                mask = dp.gather_envs(buf.params[2], dim=1)
                mask = mask.reshape(-1, mask.shape[-1])[kept] if kept is not None else mask
                stats["action_std"] = ((stds * mask).sum() / mask.sum().clamp_min(1.0)).item()
            else:
                stats["action_std"] = stds.mean().item()
            for name, dims in (self.policy.action_groups if isinstance(self.policy, GroupedActions) else {}).items():
                stats[f"action_std_{name}"] = stds[..., dims].mean().item()
        return stats

    # -- the loop --------------------------------------------------------------------------------------------------

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def train_epoch(self) -> dict[str, float]:
        """Collect ``rollout_steps`` steps from every env, update the policy; return the epoch's statistics."""
        t0 = time.perf_counter()
        stats = self.collect()
        self._sync()
        t1 = time.perf_counter()
        stats.update(self.update())
        self._sync()
        t2 = time.perf_counter()
        self.epoch += 1
        samples = self.config.rollout_steps * self.num_envs
        stats.update(
            time_rollout=t1 - t0,
            time_update=t2 - t1,
            samples_per_second=samples / max(t2 - t0, 1e-9),
            epoch=float(self.epoch),
            global_step=float(self.global_step),
        )
        if self.config.eval_every and self.eval_env is not None and self.epoch % self.config.eval_every == 0:
            stats.update(self.evaluate())
        if self.logger is not None:
            self.logger.log(stats, self.global_step)
        return stats

    @torch.no_grad()
    def evaluate(self, env: VecEnv | None = None, episodes: int | None = None) -> dict[str, float]:
        """Deterministic episodes (the distribution's mode: a Gaussian's mean) on ``env`` (default ``self.eval_env``), never the
        training env: ``eval_return`` (mean raw return), ``eval_return_std``, ``eval_length_mean``.

        ``episodes`` (default ``config.eval_episodes``) are spread over the env's environments as evenly as possible
        (env i runs ⌈(episodes − i) / n⌉ of them, as SB3's ``evaluate_policy``), so short episodes are not favoured.
        The env is reset first (seeded ``config.seed + 1`` the first time); the training generator draws nothing and
        observation statistics are applied, not updated. Data-parallel, each rank evaluates its own eval env and
        the figures are over every rank's episodes.
        """
        env = self.eval_env if env is None else env
        if env is None:
            raise ValueError("evaluate needs an env: pass one, or eval_env to PPO")
        episodes = self.config.eval_episodes if episodes is None else episodes
        n = env.num_envs
        targets = torch.tensor([(episodes + n - 1 - i) // n for i in range(n)], device=self.device)
        counts = torch.zeros(n, dtype=torch.int64, device=self.device)
        returns, lengths = [], []
        seed = None if self._eval_seeded else self.config.seed + 1
        self._eval_seeded = True
        obs = self._here(env.reset(seed=seed))
        ep_return = torch.zeros(n, device=self.device)
        ep_length = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.policy.eval()
        while bool((counts < targets).any()):
            mode = self.distribution.env_actions(self._sample(self.normalize_obs(obs), deterministic=True)[0])
            obs, reward, done, info = env.step(mode.to(env.device))
            obs, reward, done = self._here(obs), reward.to(self.device, torch.float32), done.to(self.device, torch.bool)
            moving = ~info["autoreset"].to(self.device, torch.bool) if "autoreset" in info else torch.ones_like(done)
            ep_return += reward
            ep_length += moving.to(ep_length.dtype)
            wanted = done & (counts < targets)
            if wanted.any():
                returns.append(ep_return[wanted])
                lengths.append(ep_length[wanted])
            counts += done.to(counts.dtype)
            ep_return = torch.where(done, 0.0, ep_return)
            ep_length = torch.where(done, 0, ep_length)
        all_returns = self.dp.gather_varlen(torch.cat(returns))
        all_lengths = self.dp.gather_varlen(torch.cat(lengths))
        return {
            "eval_return": all_returns.mean().item(),
            "eval_return_std": all_returns.std(correction=0).item(),
            "eval_length_mean": all_lengths.float().mean().item(),
        }

    def learn(self, epochs: int, callback: Callable[[PPO, dict[str, float]], bool | None] | None = None) -> list[dict]:
        """Train ``epochs`` epochs; ``callback(ppo, stats)`` runs after each and stops training by returning False."""
        if not isinstance(epochs, int) or epochs < 0:
            raise ValueError(f"epochs must be an int >= 0, got {epochs!r}")
        history = []
        for _ in range(epochs):
            history.append(self.train_epoch())
            if callback is not None and callback(self, history[-1]) is False:
                break
        return history

    def episodes(self) -> Episodes | None:
        """The episodes the last rollout finished, over every rank, in the design records' layout
        (``freeform.learner``; ``None`` if none finished): for envs whose episodes end in lock-step and report
        ``final_grids`` (the design envs). An episode cut by the rollout's end is carried to the next call, so call
        it after every epoch (the trainer does); a collective when data-parallel."""
        if self._collected != self.epoch - 1 and self._collector.state_dict():
            raise ValueError(f"episodes() was not called after epochs {self._collected + 1}..{self.epoch - 1}, and an "
                             "episode spans rollouts: its first steps are gone; call episodes() after every "
                             "train_epoch() (or set rollout_steps to a multiple of the episode length)")
        self._collected = self.epoch
        rollout, infos = self.dp.gather_rollout(self.rollout, self.episode_infos)
        episodes = self._collector.collect(rollout, infos)
        if episodes is not None:
            episodes["infos"] = infos
        return episodes

    # -- state and checkpoints -------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: policy, optimizer, β, counters, RNG, current obs, env state.

        What is per environment is named: it lives under ``per_env`` (``distributed.PER_ENV``; the env's own state
        names its part the same way). Data-parallel: a collective; the per-environment parts are gathered from
        every rank, so the state is the global one — loadable with any number of ranks.
        """
        state = {
            "policy": self.policy.state_dict(),
            "optimizer": self._portable_optimizer_state(),
            "kl_coeff": self.kl_coeff,
            "epoch": self.epoch,
            "global_step": self.global_step,
            "generator": self.generator.get_state(),
            PER_ENV: {"obs": self.obs, "episode_return": self.episode_return, "episode_length": self.episode_length},
            "episode_carry": self._collector.state_dict(),  # global: cut from the gathered rollout
        }
        if self.obs_rms is not None:
            state["obs_rms"] = self.obs_rms.state_dict()
        if self.return_rms is not None:
            state["return_rms"] = self.return_rms.state_dict()
            state[PER_ENV]["discounted_return"] = self.discounted_return
        if hasattr(self.env, "state_dict"):
            state["env"] = self.env.state_dict()
        return self.dp.gather_state(state)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what ``state_dict()`` returned (the policy and env must be built alike; in a data-parallel run,
        a global state of any rank count: each rank takes its slice of the environments)."""
        saved_envs = obs_first(state[PER_ENV]["obs"]).shape[0]
        if saved_envs != self.num_envs:
            raise ValueError(f"the state holds {saved_envs} envs but this run has {self.num_envs}")
        state = self.dp.shard_state(state)
        self.policy.load_state_dict(state["policy"])
        self._load_optimizer_state(self.flat.optimizer_state(state["optimizer"]))
        self.kl_coeff = float(state["kl_coeff"])
        self.epoch = int(state["epoch"])
        self.global_step = int(state["global_step"])
        self._collected = self.epoch
        self._collector.load_state_dict(state.get("episode_carry", {}))
        self.generator.set_state(state["generator"].cpu())
        per_env = state[PER_ENV]
        self.obs = self._here(per_env["obs"])
        self.episode_return = per_env["episode_return"].to(self.device)
        self.episode_length = per_env["episode_length"].to(self.device)
        for name, rms in (("obs_rms", self.obs_rms), ("return_rms", self.return_rms)):
            if rms is not None:
                if name not in state:
                    raise ValueError(f"the config normalises ({name}) but the state holds no {name} statistics")
                rms.load_state_dict(state[name])
        if self.return_rms is not None:
            self.discounted_return = per_env["discounted_return"].to(self.device, torch.float64)
        if "env" in state:
            if not hasattr(self.env, "load_state_dict"):
                raise ValueError("the state holds an env state but the env has no load_state_dict()")
            self.env.load_state_dict(state["env"])

    def _portable_optimizer_state(self) -> dict[str, Any]:
        """The optimizer's state as the eager Adam holds it (lr a float, the step count on the CPU, not capturable),
        whichever way this PPO runs: one checkpoint format, loadable by an eager or a graphed PPO."""
        state = self.optimizer.state_dict()
        if not self.config.cuda_graph:
            return state
        groups = [{**g, "lr": float(g["lr"]), "capturable": False} for g in state["param_groups"]]
        moments = {i: {k: (v.cpu() if k == "step" else v) for k, v in s.items()} for i, s in state["state"].items()}
        return {"state": moments, "param_groups": groups}

    def _load_optimizer_state(self, state: dict[str, Any]) -> None:
        """Load a portable optimizer state (:meth:`_portable_optimizer_state`) into this PPO's Adam as it runs."""
        capturable = self.config.cuda_graph
        groups = [{**g, "capturable": capturable} for g in state["param_groups"]]
        # Copies: torch's load keeps a tensor that is already on the right device, so the moments would otherwise be
        # shared with the state's owner (another PPO, after ppo.load_state_dict(other.state_dict())) and both trained.
        moments = {i: {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in s.items()}
                   for i, s in state["state"].items()}
        self.optimizer.load_state_dict({"state": moments, "param_groups": groups})  # capturable: step to the device
        for group in self.optimizer.param_groups:
            group["lr"] = self._lr_value(float(group["lr"]))
        if self._graphed is not None:
            self._graphed.reset()  # the graph read the old state's tensors

    def checkpoint(self) -> dict[str, Any]:
        """A self-describing checkpoint's content: the policy's class name and constructor arguments, this
        ``PPOConfig`` and the training state (a collective when data-parallel). The trainer's run checkpoints are
        this plus the run's own parts, so :meth:`load` reads both."""
        return {
            "policy_class": policy_class_name(type(self.policy)),
            "policy_kwargs": dict(self.policy.init_kwargs if isinstance(self.policy, Rebuildable) else {}),
            "ppo_config": dataclasses.asdict(self.config),
            "epoch": self.epoch,
            "global_step": self.global_step,
            "ppo": self.state_dict(),
        }

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Continue from a checkpoint :meth:`checkpoint` wrote (the ``Learner`` protocol): ``load_state_dict`` of
        its ``ppo`` part."""
        self.load_state_dict(checkpoint["ppo"])

    def save(self, path: str | os.PathLike) -> None:
        """Write :meth:`checkpoint` atomically (``freeform.checkpoint.save_checkpoint``).

        Data-parallel: every rank calls it (the state is gathered); rank 0 writes.
        """
        payload = self.checkpoint()
        if self.dp.is_writer:
            save_checkpoint(path, payload)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        env: VecEnv,
        logger: ScalarSink | None = None,
        device: str | None = None,
        policy_classes: Sequence[type[nn.Module]] = (),
    ) -> PPO:
        """Rebuild a PPO (policy, config, full training state) from a file of :meth:`save` or a run's checkpoint.

        The file names its policy class; it is built only if it is one of freeform's networks or in
        ``policy_classes`` (the caller's own, allowed explicitly): loading never imports what a file names, and the
        file itself is read with ``weights_only`` (no code runs). ``device`` overrides the saved ``config.device``.
        Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file for a corrupt or
        incompatible one.
        """
        payload = load_checkpoint(path)
        allowed = {policy_class_name(c): c for c in (*builtin_policies(), *policy_classes)}
        try:
            name = payload["policy_class"]
            if name not in allowed:
                raise CheckpointError(
                    f"{path}: its policy class {name!r} is not one of freeform's networks; pass "
                    f"policy_classes=[<that class>] to PPO.load to build it"
                )
            policy = allowed[name](**payload["policy_kwargs"])
            config_dict = dict(payload["ppo_config"])
            if device is not None:
                config_dict["device"] = device
            config = PPOConfig(**config_dict)
        except CheckpointError:
            raise
        except Exception as e:
            raise CheckpointError(f"{path}: cannot rebuild the policy/config ({type(e).__name__}: {e})") from e
        state = payload["ppo"]
        saved_obs = state[PER_ENV]["obs"]

        saved_envs = obs_first(saved_obs).shape[0]
        saved_shape = obs_map(lambda x: x[0], saved_obs)  # one env's observation: its shape is the env's
        shape = obs_shapes(saved_shape)
        wanted = env.observation_shape
        wanted = {k: tuple(v) for k, v in wanted.items()} if isinstance(wanted, Mapping) else tuple(wanted)

        def check_envs(num_envs: int) -> None:
            if saved_envs != num_envs or shape != wanted:
                raise CheckpointError(
                    f"{path}: saved for {saved_envs} envs with observations {shape}, "
                    f"but the env has {num_envs} envs with observations {wanted}"
                )

        if not distributed.is_distributed():
            check_envs(env.num_envs)
        try:
            ppo = cls(env, policy, config, logger)
        except ValueError as e:
            raise CheckpointError(f"{path}: the saved policy does not fit this env ({e})") from e
        check_envs(ppo.num_envs)  # data-parallel: the global count (a collective in the constructor learnt it)
        try:
            ppo.load_state_dict(state)
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"{path}: incompatible training state ({type(e).__name__}: {e})") from e
        return ppo


def choose_distribution(policy: nn.Module, env: VecEnv) -> ActionDistribution:
    """The action distribution PPO trains, decided once: the one the policy declares (``distribution``, e.g.
    ``MLPActorCritic``'s), else the env's (``action_distribution``: ``from_gymnasium`` sets it from the action space),
    else a diagonal Gaussian over ``env.action_dim`` floats (the design env). Both declared and different, or an
    action size other than the env's, is an error naming the two."""
    declared = policy.distribution if isinstance(policy, DeclaresDistribution) else None
    offered = getattr(env, "action_distribution", None)
    if declared is not None and offered is not None and declared != offered:
        raise ValueError(f"the policy outputs a {declared} but the env's actions need a {offered}")
    dist = declared or offered or DiagGaussian(int(env.action_dim))
    if not isinstance(dist, ActionDistribution):
        raise ValueError(f"an action distribution must be a freeform.agents.distributions.ActionDistribution, got {dist!r}")
    if dist.action_dim != env.action_dim:
        raise ValueError(f"the {dist} gives {dist.action_dim} numbers per action but the env takes {env.action_dim}")
    return dist


def policy_class_name(cls: type) -> str:
    """How a checkpoint names a policy class: ``module:qualname``."""
    return f"{cls.__module__}:{cls.__qualname__}"


def builtin_policies() -> tuple[type[nn.Module], ...]:
    """The networks any checkpoint may name (freeform's own)."""
    from freeform.agents.networks import (
        CodesignActorCritic,
        ConvController,
        MLPActorCritic,
        MLPController,
        VoxelActorCritic,
    )

    return (VoxelActorCritic, MLPActorCritic, ConvController, MLPController, CodesignActorCritic)


__all__ = ["PPO", "builtin_policies", "choose_distribution", "policy_class_name"]
