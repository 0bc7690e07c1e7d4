"""Batched PPO: the public class. Its parts follow the data — ``collect.py`` (rollout collection), ``update.py``
(minibatch SGD and the KL rule), ``checkpoints.py`` (state, save, load) —, each a part of :class:`PPO`; the
algorithm reads top to bottom: rollout → returns/advantages → loss → update → KL schedule.

The default configuration reproduces the semantics of RLlib 2.0.1's PPO as the paper used it (spec ``ppo.md``):
GAE with λ = 1 (advantage = discounted return − V), advantages standardised once over the whole train batch, the
clipped surrogate, the squared value error clamped at ``vf_clip_param``, a KL(π_old ‖ π) penalty whose coefficient
adapts after every epoch, Adam without gradient clipping. Common variants are switches in ``PPOConfig``.

Shapes: ``T`` = ``rollout_steps``, ``N`` = ``env.num_envs``, ``A`` = ``env.action_dim``, ``B`` = ``T·N``.

The action distribution (``freeform.distributions``: a Gaussian for Box actions, categoricals or bits for
discrete ones) is decided once, at construction, from the policy or the env (:func:`choose_distribution`); below,
``self.distribution`` samples, scores and compares actions, and only the logged σ (a Gaussian's own figure) asks
which one it is.

Every collective sits behind ``self.dp`` (``freeform.agents.distributed.Collectives``), the identity in one process:
the code below is the single-process algorithm. Under ``torch.distributed`` (a process group of R > 1 ranks, e.g.
``torchrun``) each rank's env holds its slice of the environments, ``self.dp`` is a ``DataParallel`` and the update
uses the statistics of the global batch; the rules are in ``distributed.py`` (``docs/scaling.md``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import torch
import torch.nn as nn

from freeform.agents import distributed
from freeform.agents.networks import DeclaresDistribution, SplitActorCritic
from freeform.agents.networks.observation_groups import GROUPS, is_grouped, without_critic
from freeform.agents.networks.recurrent import RecurrentPolicy
from freeform.agents.ppo.checkpoints import Checkpoints, builtin_policies, policy_class_name
from freeform.agents.ppo.collect import RolloutCollection
from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.flat_params import FlatParameters
from freeform.agents.ppo.graphed import GraphedMinibatchStep
from freeform.agents.ppo.losses import minibatch_loss
from freeform.agents.ppo.normalization import RunningMeanStd
from freeform.agents.ppo.rollout import Observation, Rollout, obs_first, obs_map, obs_shapes
from freeform.agents.ppo.update import MinibatchUpdate, own_code
from freeform.distributions import ActionDistribution, DiagGaussian, MaskedDiagGaussian
from freeform.envs.base import VecEnv
from freeform.learner import Episodes
from freeform.records import EpisodeCollector

if TYPE_CHECKING:  # (the TensorBoard writer is not imported with PPO)
    from freeform.logger import ScalarSink


class PPO(RolloutCollection, MinibatchUpdate, Checkpoints):
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
        self.config = config = _checked(config, env)
        self.env = env
        self.device = torch.device(config.device) if config.device is not None else torch.device(env.device)
        self.logger = logger
        self._take_policy(policy)
        self._build_optimizer()
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.kl_coeff = float(config.kl_coeff)
        self.epoch = 0
        self.global_step = 0

        self.eval_env = eval_env
        """Where ``evaluate`` runs (every ``config.eval_every`` epochs); None = no evaluation."""
        self._eval_seeded = False
        self._build_normalizers()
        self._start_rollouts()

    def _take_policy(self, policy: nn.Module) -> None:
        """The policy on the device (the same weights on every rank), the distribution it parameterises, and what
        kind of policy it is (recurrent, actor apart from critic, reading observation groups)."""
        config, env = self.config, self.env
        self.policy = policy.to(self.device)
        self.dp = distributed.collectives(env.num_envs, self.device)
        self.dp.broadcast_module_(self.policy)  # identical starting weights, whatever each rank's RNG did
        self.num_envs = self.dp.num_envs
        """N, environments over all ranks (= ``env.num_envs`` in one process)."""
        self.distribution = choose_distribution(policy, env)
        """The action distribution π(·|obs): the policy outputs its parameters (``param_dims``), then V."""
        if config.obs_norm and isinstance(self.distribution, MaskedDiagGaussian):
            raise ValueError("obs_norm would rescale the observation channel that the policy reads its action mask "
                             "from (a MaskedDiagGaussian's mask must stay 0/1): leave obs_norm off for a control env")
        self.recurrent = isinstance(policy, RecurrentPolicy)
        """The policy has memory (``freeform.agents.networks.recurrent``): PPO carries its state and trains on sequences."""
        if self.recurrent:
            _refuse_for_recurrent(config)
        self.critic_apart = isinstance(policy, SplitActorCritic) and not self.recurrent
        """The policy has ``action_params``/``value`` (actor and critic share nothing): the rollout runs the actor per
        step and the critic once over the rollout (``networks.py``)."""
        self.grouped = is_grouped(env.observation_shape)
        """The env observes the groups ``"policy"`` and ``"critic"`` (``observation_groups.py``): the actor must read
        ``"policy"`` alone, so the policy runs its halves apart."""
        if self.grouped and not (self.critic_apart or self.recurrent):
            raise ValueError(f"this env observes the groups {GROUPS}, of which the actor may read only 'policy': "
                             f"{type(policy).__name__} must run its actor apart from its critic (action_params(obs) "
                             "and value(obs), as MLPActorCritic.for_env(env)'s GroupedMLPActorCritic does)")
        grouped = config.group_baseline or config.advantage_norm == "group"
        self.reward_groups = _reward_groups(env, self.device) if grouped else None
        """``group_baseline``, ``advantage_norm="group"``: each env's group (``env.reward_groups``), int64 ``[N]``
        on the policy's device."""

    def _build_optimizer(self) -> None:
        """Adam over the policy's parameters as one flat tensor, the minibatch loss (compiled where asked) and the
        minibatch step's CUDA graph (``agent.cuda_graph``)."""
        config = self.config
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
        self._minibatch_loss = torch.compile(own_code(minibatch_loss), dynamic=False) if config.compile else minibatch_loss
        self._graphed = (GraphedMinibatchStep(self.policy, self.distribution, config, self.flat, self.optimizer,
                                              self._minibatch_mean, self.device) if config.cuda_graph else None)
        """The minibatch step as a CUDA graph (``agent.cuda_graph``), else None: the eager step in ``_sgd``."""

    def _build_normalizers(self) -> None:
        """Running statistics of the optional normalisations (None when off, the paper's case)."""
        config, obs_shape = self.config, self.env.observation_shape
        self.obs_rms: RunningMeanStd | dict[str, RunningMeanStd] | None = None
        """``obs_norm``'s running statistics: one, or one per part of a dict observation (per group)."""
        if config.obs_norm:
            self.obs_rms = ({k: RunningMeanStd(tuple(s), self.device) for k, s in obs_shape.items()}
                            if isinstance(obs_shape, Mapping) else RunningMeanStd(tuple(obs_shape), self.device))
        self.return_rms = RunningMeanStd((), self.device) if config.reward_norm else None
        # float64 as the statistics (Gymnasium's too); only with reward_norm, as no float64 may exist (MPS)
        self.discounted_return = torch.zeros(self.env.num_envs, device=self.device,
                                             dtype=torch.float64 if config.reward_norm else torch.float32)
        """Each env's discounted return of raw rewards, whose running std scales the rewards (``reward_norm``)."""

    def _start_rollouts(self) -> None:
        """The env reset (seeded), the policy checked against it, and the rollout storage and episode counters."""
        config, env = self.config, self.env
        self.obs = self._here(env.reset(seed=config.seed))
        self._update_obs_rms(self.obs)
        self.policy_state: tuple[torch.Tensor, ...] = ()
        """A recurrent policy's state after the last observation it read, ``[N, ...]`` each (empty: feed-forward)."""
        self.episode_start = torch.ones(env.num_envs, dtype=torch.bool, device=self.device)
        """``[N]`` bool: the current observation begins an episode (a recurrent policy resets its state first)."""
        if self.recurrent:
            self.policy_state = tuple(x.to(self.device) for x in self.policy.initial_state(env.num_envs))
            self._check_recurrent_policy()
        else:
            self._check_policy()
        obs_dtype = torch.float32 if self.obs_rms is not None else None
        self.rollout = Rollout.allocate(config.rollout_steps, env.num_envs, self.obs, obs_dtype, env.action_dim,
                                        self.distribution.param_dims, self.device, self.policy_state)
        self.episode_infos: list[dict[str, Any]] = []
        self._collector = EpisodeCollector()  # episodes() cuts the rollouts; its carry is part of the state
        self._collected = 0  # the epoch count at the last episodes() call
        # Running return and length of each env's current episode (they span epochs when episodes are cut).
        self.episode_return = torch.zeros(env.num_envs, dtype=torch.float32, device=self.device)
        self.episode_length = torch.zeros(env.num_envs, dtype=torch.int64, device=self.device)
        # The latest finished episodes' returns and lengths (global, on the CPU): PPOConfig.stats_window's.
        self.recent_returns = torch.zeros(0, dtype=torch.float32)
        self.recent_lengths = torch.zeros(0, dtype=torch.int64)

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
        if self.grouped:  # the actor on the policy group alone: it must not need, nor read, the critic's
            try:
                alone = self.policy.action_params(without_critic(self.normalize_obs(self.obs)))
            except KeyError as e:
                raise ValueError(f"the actor of {type(self.policy).__name__} reads {e} of the observation, and it may "
                                 "read only the 'policy' group (the 'critic' group is the critic's)") from e
            if not all(torch.equal(a, o) for a, o in zip(alone, outputs, strict=False)):
                raise ValueError(f"the actor of {type(self.policy).__name__} gives other actions without the "
                                 "'critic' group: it may read only the 'policy' group")

    @torch.no_grad()
    def _check_recurrent_policy(self) -> None:
        """:meth:`_check_policy` for a recurrent policy: one step of ``forward(obs [1, N, ...], state, episode_start
        [1, N])`` must give the distribution's parameters ``[1, N, P_i]``, the value ``[1, N]`` and a state of the
        initial state's shapes."""
        n, dist = self.env.num_envs, self.distribution
        try:
            outputs = self.policy(obs_map(lambda x: x[None], self.normalize_obs(self.obs)), self.policy_state,
                                  self.episode_start[None])
        except Exception as e:
            raise ValueError(f"recurrent policy cannot read the env's observations {obs_shapes(self.obs)} with its "
                             f"initial state ({type(e).__name__}: {e})") from e
        wanted = [(1, n, p) for p in dist.param_dims] + [(1, n)]
        shapes = [tuple(x.shape) for x in outputs[:-1]] if isinstance(outputs, tuple) else None
        states = [tuple(x.shape) for x in outputs[-1]] if isinstance(outputs, tuple) else None
        if shapes != wanted or states != [tuple(x.shape) for x in self.policy_state]:
            raise ValueError(f"a recurrent policy must return its {dist} parameters, the value ({wanted}) and its state "
                             f"{[tuple(x.shape) for x in self.policy_state]}, got {shapes} and {states}")

    @torch.no_grad()
    def act(self, obs: Observation, state: tuple[torch.Tensor, ...] | None = None,
            episode_start: torch.Tensor | None = None, deterministic: bool = False) -> Any:
        """Actions ``[N, A]`` for raw observations ``[N, ...]`` (the distribution's mode if ``deterministic``: a
        Gaussian's mean), on the env's device, as the env takes them (int64 for a discrete distribution).

        A recurrent policy returns ``(actions, state)``: ``state`` is what the previous call returned (None: every
        env starts an episode), ``episode_start [N]`` bool marks the envs whose observation begins an episode (their
        state is reset first; None: all where ``state`` is None, else none). A feed-forward policy takes neither.

        With ``obs_norm`` the observations are normalised by the saved statistics (not updated). Sampling draws from
        the training generator, so calls between epochs shift the training's random stream.
        """
        x = self.normalize_obs(self._here(obs))
        if not self.recurrent:
            if state is not None or episode_start is not None:
                raise ValueError(f"state and episode_start are a recurrent policy's, and {type(self.policy).__name__} "
                                 "is feed-forward (pass deterministic by name: act(obs, deterministic=True))")
            return self.distribution.env_actions(self._sample(x, deterministic)[0]).to(self.env.device)
        n = obs_first(x).shape[0]
        if episode_start is None:
            episode_start = torch.full((n,), state is None, dtype=torch.bool, device=self.device)
        if state is None:
            state = tuple(s.to(self.device) for s in self.policy.initial_state(n))
        action, _, _, state = self._sample_recurrent(x, tuple(state), self._here(episode_start).bool(), deterministic)
        return self.distribution.env_actions(action).to(self.env.device), state

    def episode_actor(self, deterministic: bool = False) -> Callable[[Observation], torch.Tensor]:
        """``act`` as a function of the observation alone, for one batch of episodes that all start at its first
        call (an env's ``reset``): a recurrent policy's state is carried from call to call inside it, a
        feed-forward policy's calls are ``act``'s. Make a new one for the next episodes."""
        if not self.recurrent:
            return lambda obs: self.act(obs, deterministic=deterministic)
        state = None

        def actor(obs: Observation) -> torch.Tensor:
            nonlocal state
            actions, state = self.act(obs, state, deterministic=deterministic)
            return actions

        return actor

    def export(self, path: str | os.PathLike, opset: int | None = None) -> str:
        """Write the actor's deterministic action to ``path`` as ONNX, observation normalisation folded in: the file
        takes raw observations and returns what ``act(obs, deterministic=True)`` does (inputs, outputs and what
        cannot be exported: ``freeform.agents.ppo.export``). Needs the ``export`` extra; returns the path."""
        from freeform.agents.ppo.export import export_onnx

        return export_onnx(self, path, opset)

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
        The env is reset first (seeded ``config.seed + 1`` the first time, or every time with
        ``config.eval_same_episodes``); the training generator draws nothing and
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
        seed = None if self._eval_seeded and not self.config.eval_same_episodes else self.config.seed + 1
        self._eval_seeded = True
        obs = self._here(env.reset(seed=seed))
        ep_return = torch.zeros(n, device=self.device)
        ep_length = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.policy.eval()
        state = tuple(s.to(self.device) for s in self.policy.initial_state(n)) if self.recurrent else ()
        start = torch.ones(n, dtype=torch.bool, device=self.device)
        while bool((counts < targets).any()):
            if self.recurrent:
                mode, _, _, state = self._sample_recurrent(self.normalize_obs(obs), state, start, deterministic=True)
            else:
                mode = self._sample(self.normalize_obs(obs), deterministic=True)[0]
            obs, reward, done, info = env.step(self.distribution.env_actions(mode).to(env.device))
            obs, reward, done = self._here(obs), reward.to(self.device, torch.float32), done.to(self.device, torch.bool)
            moving = ~info["autoreset"].to(self.device, torch.bool) if "autoreset" in info else torch.ones_like(done)
            start = done | ~moving
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


def _checked(config: PPOConfig | None, env: VecEnv) -> PPOConfig:
    """``config`` (None: the defaults), refused unless a ``PPOConfig``; ``env`` refused unless a ``VecEnv``."""
    config = config if config is not None else PPOConfig()
    if not isinstance(config, PPOConfig):
        raise ValueError(f"config must be a PPOConfig, got {type(config).__name__}")
    for attr in ("num_envs", "observation_shape", "action_dim", "reset", "step"):
        if not hasattr(env, attr):
            raise ValueError(f"env must follow freeform.envs.VecEnv; it has no {attr!r}")
    return config


def _refuse_for_recurrent(config: PPOConfig) -> None:
    """What a recurrent policy cannot run with, refused with the reason."""
    if config.cuda_graph:
        raise ValueError("agent.cuda_graph captures the feed-forward minibatch step, and a recurrent policy's step runs "
                         "a sequence whose resets vary: set agent.cuda_graph=false")
    if config.compile:
        raise ValueError("agent.compile compiles the feed-forward minibatch loss, not the sequence loss of a recurrent "
                         "policy: set agent.compile=false")


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
        raise ValueError(f"an action distribution must be a freeform.distributions.ActionDistribution, got {dist!r}")
    if dist.action_dim != env.action_dim:
        raise ValueError(f"the {dist} gives {dist.action_dim} numbers per action but the env takes {env.action_dim}")
    return dist



def _reward_groups(env: VecEnv, device: torch.device) -> torch.Tensor:
    """``env.reward_groups`` checked for ``group_baseline``: ids ``0 … G−1`` of ``[num_envs]``, each used >= 2 times."""
    groups = getattr(env, "reward_groups", None)
    if groups is None:
        raise ValueError(f"agent.group_baseline needs an env that names each environment's group of copies "
                         f"(env.reward_groups), and {type(env).__name__} has none: use control.bodies=population "
                         "with control.copies >= 2, or set agent.group_baseline=false")
    groups = torch.as_tensor(groups, device=device).long()
    count = torch.bincount(groups) if groups.numel() and int(groups.min()) >= 0 else None
    if groups.shape != (env.num_envs,) or count is None or int(count.min()) < 2:
        raise ValueError(f"env.reward_groups must give each of the {env.num_envs} environments a group id 0..G-1 "
                         f"used by >= 2 environments (copies), got {groups.tolist()}")
    return groups

__all__ = ["PPO", "builtin_policies", "choose_distribution", "policy_class_name"]
