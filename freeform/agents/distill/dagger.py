"""Distillation (issue 56): DAgger from teachers per environment into one student policy.

DAgger (Ross, Gordon & Bagnell 2011; rsl_rl's ``Distillation``): each epoch is a round. The student acts — in round
r each environment's step takes its teacher's action instead with probability β_r = ``beta`` · ``beta_decay``^r
(the teachers lead early, the student alone later) — and every observation the student visits is labelled with the
teacher's action distribution on it. The labelled samples join a dataset that aggregates the last ``buffer``
rounds, and the student regresses onto the labels: ``kl`` minimises KL(teacher ‖ student) of the action
distributions (the student's σ learns the teacher's), ``mse`` the squared error of the means (σ is left as it is).
The student's critic regresses onto the teacher's value (weight ``agent.vf_loss_coeff``), so that a PPO fine-tune
from the student's weights (``control.controller_init=<this run>``) starts with a critic.

A teacher is any policy per environment index (:class:`Teacher`): ``teacher(obs [N, ...], envs [N]) -> (*params,
value)`` in the student's distribution — a bank of per-body controllers (:class:`BankTeacher`), or any callable, so
distillation works for any ``VecEnv``. Collection, episodes, checkpoints, resume, data parallelism and logging are
PPO's (the learner is a :class:`~freeform.agents.PPO` whose update is the regression); the dataset is
per-environment state (``per_env``), so a checkpoint resumes it exactly, on any number of ranks.

A recurrent student (``freeform.agents.networks.recurrent``: ``context_gru``, ``RecurrentActorCritic``) learns over sequences:
the dataset keeps each env's steps in order with its episode starts, and the regression runs chunks of
``agent.sequence_length`` steps from the student's state at their first step (truncated BPTT, as PPO trains it).
The teacher still labels single observations — it may read what the student cannot (the observation groups'
``"critic"``: a privileged teacher), and a student with memory can then infer from its observations over time
what the teacher sees at once (rsl_rl's privileged teacher and recurrent student).

Shapes: ``T`` = ``rollout_steps``, ``N`` = environments, ``K`` = ``buffer · T`` samples kept per environment.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from contextlib import nullcontext
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, Protocol

import torch
import torch.nn as nn

from freeform.agents.distill.teachers import TEACHER, TeacherBank
from freeform.agents.distributed import PER_ENV
from freeform.agents.networks.observation_groups import POLICY
from freeform.agents.ppo import PPO, PPOConfig
from freeform.agents.ppo.losses import masked_mean
from freeform.agents.ppo.rollout import Observation, chunked, obs_map
from freeform.distributions import ActionDistribution, DiagGaussian

LOSSES = ("kl", "mse")
STEP_FLAGS = ("starts", "valid")
"""What a recurrent student's dataset keeps of each step besides its sample: ``[N, K]`` bool each."""


@dataclass
class DistillConfig:
    """DAgger's settings (``algo.*`` of a run with ``algo.name=distill``); the student's SGD is the ``agent``
    section's (``lr``, ``num_sgd_iter`` passes over the dataset each round, ``sgd_minibatch_size``,
    ``grad_clip``, ``vf_loss_coeff``)."""

    loss: str = "kl"
    """``kl``: KL(teacher ‖ student) of the action distributions; ``mse``: the means' squared error."""
    beta: float = 1.0
    """Round 0's probability that a step takes the teacher's action (its mean) instead of the student's."""
    beta_decay: float = 0.5
    """β_r = beta · beta_decay^r."""
    buffer: int = 4
    """Rounds (epochs) of labelled samples the dataset keeps (the oldest leave first)."""
    symmetry: str = "none"
    """``none``, or the name of a group of the env's symmetries (a control env's: ``ground`` — its turns and
    mirrors —, ``mirror`` — y → −y alone; ``freeform.envs.symmetry.GROUPS``): each regression sample turned by a
    random element of it, its observation and its label alike (:class:`Symmetry`), so that one labelled body
    teaches its turned and mirrored selves too."""
    token_dropout: float = 0.0
    """The probability that a regression sample's voxel is hidden from the rest of its body (a voxel-token
    student's :meth:`~freeform.agents.networks.attention_controllers.VoxelAttentionController.hiding`; each cell of each
    sample drawn apart, every round): the student learns the label's gait from parts of the body, a regulariser of
    the map from shapes to gaits. Feed-forward voxel-token students only; 0: none (no draw)."""

    def validate(self, key: str = "algo") -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"{key}.loss must be one of {LOSSES}, got {self.loss!r}")
        for name in ("beta", "beta_decay"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
                raise ValueError(f"{key}.{name} must be a probability in [0, 1], got {value!r}")
        if not (isinstance(self.buffer, int) and self.buffer >= 1):
            raise ValueError(f"{key}.buffer must be an integer >= 1 (rounds kept), got {self.buffer!r}")
        if not (isinstance(self.token_dropout, (int, float)) and 0.0 <= self.token_dropout < 1.0):
            raise ValueError(f"{key}.token_dropout must be a probability in [0, 1) (0: none), got "
                             f"{self.token_dropout!r}")
        if not (isinstance(self.symmetry, str) and self.symmetry):
            raise ValueError(f"{key}.symmetry must be 'none' or a group of the env's symmetries (a control env's: "
                             f"'ground', 'mirror'), got {self.symmetry!r}")

    @classmethod
    def from_algo(cls, algo: Any) -> DistillConfig:
        """The fields of a run's ``algo`` section (``freeform.evolve.config.AlgoConfig``) that are DAgger's."""
        return cls(loss=algo.loss, beta=algo.beta, beta_decay=algo.beta_decay, buffer=algo.buffer,
                   symmetry=algo.symmetry, token_dropout=algo.token_dropout)

    def beta_at(self, round_: int) -> float:
        return float(self.beta * self.beta_decay ** round_)


class Teacher(Protocol):
    """A policy per environment: ``(obs [N, ...], envs [N] int64, each sample's environment) -> (*params, value)``,
    ``params`` the student's distribution's (``value`` ``[N]``, or None where the teacher has no critic). ``envs``
    index this process's environments: data-parallel, index i is environment ``first_env + i`` of the run."""

    def __call__(self, obs: Observation, envs: torch.Tensor) -> tuple[torch.Tensor | None, ...]: ...


class Symmetry(Protocol):
    """A group of transformations under which the task is unchanged (``DistillConfig.symmetry``): ``size``
    elements, element 0 the identity; ``observations(obs [N, ...], g [N])`` turns sample n by element ``g[n]``,
    ``cells(x [N, A], g)`` a distribution parameter's entries the same way (a control env's:
    ``freeform.envs.symmetry.PlanarSymmetry``)."""

    size: int

    def observations(self, obs: torch.Tensor, g: torch.Tensor) -> torch.Tensor: ...

    def cells(self, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor: ...


class BankTeacher:
    """A :class:`~freeform.agents.distill.teachers.TeacherBank` as a :class:`Teacher`: environment i is taught by teacher
    ``of_env[i]`` (a control run of M bodies repeated in turn: ``i mod M``)."""

    def __init__(self, bank: TeacherBank, of_env: torch.Tensor) -> None:
        self.bank, self.of_env = bank.eval(), torch.as_tensor(of_env, dtype=torch.long)

    @torch.no_grad()
    def __call__(self, obs: Observation, envs: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        groups = dict(obs) if isinstance(obs, Mapping) else {"policy": obs}
        return tuple(self.bank({TEACHER: self.of_env.to(envs.device)[envs], **groups}))


class ChosenTeacher:
    """Several saved controllers as a :class:`Teacher`: environment i is taught by controller
    ``choice[of_env[i]]`` — each body's own controller among them, chosen by trial (``python -m lab.selection
    --try``: a teacher for every body at the cost of one episode a controller, where a trained teacher costs
    epochs). Feed-forward controllers of the run's observation (its ``"policy"`` group); each labels its own rows."""

    def __init__(self, controllers: list[nn.Module], choice: torch.Tensor, of_env: torch.Tensor) -> None:
        self.controllers = [c.eval() for c in controllers]
        self.choice = torch.as_tensor(choice, dtype=torch.long)
        self.of_env = torch.as_tensor(of_env, dtype=torch.long)
        if self.choice.numel() and not 0 <= int(self.choice.min()) <= int(self.choice.max()) < len(controllers):
            raise ValueError(f"a body's chosen controller must be one of the {len(controllers)} given")

    @torch.no_grad()
    def __call__(self, obs: Observation, envs: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        policy = obs[POLICY] if isinstance(obs, Mapping) else obs
        who = self.choice.to(envs.device)[self.of_env.to(envs.device)[envs]]
        out: list[torch.Tensor] | None = None
        for c in torch.unique(who).tolist():
            rows = (who == c).nonzero().squeeze(1)
            part = self.controllers[c](policy[rows])
            if out is None:
                out = [p.new_zeros((len(who), *p.shape[1:])) for p in part]
            for o, p in zip(out, part, strict=True):
                o[rows] = p
        assert out is not None, "no environments to label"
        return tuple(out)


class TeacherMixing:
    """A ``VecEnv`` whose step takes, for each environment with probability ``beta``, its teacher's action (the
    mean) instead of the one given: DAgger's mixture policy. The draws are a function of ``(seed, step, global
    environment index)`` — ``step`` counts this env's steps since the start, set by the learner from its own step
    count — so a resumed or data-parallel run draws what one process would. ``first_env``, ``total_envs``: this
    slice's place among all environments. Everything else is the env's."""

    def __init__(self, env: Any, teacher: Teacher, distribution: ActionDistribution | None, seed: int,
                 first_env: int = 0, total_envs: int | None = None) -> None:
        self.env, self.teacher, self.distribution = env, teacher, distribution
        self.num_envs, self.action_dim, self.device = env.num_envs, env.action_dim, env.device
        self.observation_shape = env.observation_shape
        self.seed, self.first_env = seed, first_env
        self.total_envs = total_envs if total_envs is not None else env.num_envs
        self.beta, self.step_count = 0.0, 0
        self.mixed = 0.0
        """The fraction of the last rollout's steps that took the teacher's action, over every rank's environments
        (a statistic)."""
        self._obs: Observation | None = None

    def __getattr__(self, name: str) -> Any:
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(self, seed: int | None = None) -> Observation:
        self._obs = self.env.reset(seed)
        return self._obs

    def resume(self, obs: Observation) -> None:
        """The observation the next step acts on (a restored run's: it does not reset)."""
        self._obs = obs

    def step(self, actions: torch.Tensor) -> tuple[Observation, torch.Tensor, torch.Tensor, dict[str, Any]]:
        if self.beta > 0.0 and self._obs is not None:
            g = torch.Generator().manual_seed(int(self.seed) * 1_000_003 + self.step_count)
            every = torch.rand(self.total_envs, generator=g) < self.beta  # (every rank draws all: the global figure)
            take = every[self.first_env: self.first_env + self.num_envs]
            if bool(take.any()):
                envs = torch.arange(self.num_envs, device=self.device)
                *params, _ = self.teacher(self._obs, envs)
                taught = self.distribution.env_actions(self.distribution.mode(tuple(params))).to(actions.device)
                actions = torch.where(take.to(actions.device)[:, None], taught.to(actions.dtype), actions)
            self.mixed += float(every.float().mean())
        self.step_count += 1
        obs, reward, done, info = self.env.step(actions)
        self._obs = obs
        return obs, reward, done, info


def distill_loss(student: tuple[torch.Tensor, ...], teacher: tuple[torch.Tensor, ...],
                 teacher_value: torch.Tensor, dist: ActionDistribution, loss: str, vf_coeff: float,
                 reduce: Callable[[torch.Tensor], torch.Tensor] = torch.mean) -> tuple[torch.Tensor, torch.Tensor]:
    """The regression's loss on M samples and its statistics ``[4]`` (detached: the action loss, KL(teacher ‖
    student), the means' squared error, the value loss). ``student``: the student's ``(*params, value)``;
    ``teacher``: the teacher's params; ``teacher_value [M]`` (NaN where the teacher has no critic: no value
    loss); ``reduce``: the minibatch mean (``Collectives.minibatch_mean``)."""
    *params, value = student
    kl = reduce(dist.kl(tuple(teacher), tuple(params)))
    mse = reduce((dist.mode(tuple(params)) - dist.mode(tuple(teacher))).pow(2).mean(-1))
    taught = ~torch.isnan(teacher_value)
    value_loss = reduce(torch.where(taught, value - teacher_value.nan_to_num(), 0.0).pow(2))
    action = kl if loss == "kl" else mse
    return action + vf_coeff * value_loss, torch.stack([action, kl, mse, value_loss]).detach()


class _Sequences(NamedTuple):
    """A recurrent student's view of the dataset: each env's K steps cut into C chunks of L (the last padded),
    sequence ``s = c·N + n`` env n's chunk c, time-major — ``obs [L, S, ...]``, the labels ``params`` (each ``[L, S,
    ...]``) and ``value [L, S]``, ``starts [L, S]`` bool (the state is reset before such a step), ``mask [L, S]``
    bool (the steps that count), ``state`` the student's at each chunk's first step (``[S, ...]`` each); this
    rank's, with ``counted`` the mask of every rank's sequences (``[L, C·N_global]``)."""

    obs: Observation
    params: list[torch.Tensor]
    value: torch.Tensor
    starts: torch.Tensor
    mask: torch.Tensor
    state: tuple[torch.Tensor, ...]
    counted: torch.Tensor


class Distillation(PPO):
    """DAgger into ``student`` (any policy PPO trains: ``forward(obs) -> (*params, value)``) from ``teacher``
    (module docstring). ``config``: the student's SGD (PPO's fields that apply); ``distill``: DAgger's.
    ``first_env``, ``total_envs``: a data-parallel rank's slice (the teacher's draws and indices are global). With
    ``distill.symmetry`` the env gives the group by that name: ``env.symmetry(name)`` (:class:`Symmetry`; a control
    env's)."""

    def __init__(self, env: Any, student: nn.Module, teacher: Teacher, config: PPOConfig,
                 distill: DistillConfig | None = None, logger: Any = None, first_env: int = 0,
                 total_envs: int | None = None) -> None:
        self.distill = distill or DistillConfig()
        self.distill.validate()
        self.symmetry: Symmetry | None = None
        if self.distill.symmetry != "none":
            if not callable(getattr(env, "symmetry", None)):
                raise ValueError(f"algo.symmetry={self.distill.symmetry} needs an env that declares its symmetry "
                                 f"groups (env.symmetry(name), as a control env does); {type(env).__name__} has none")
            self.symmetry = env.symmetry(self.distill.symmetry)
        if config.obs_norm:
            raise ValueError("distillation labels the observations a teacher sees: set agent.obs_norm=false")
        # (the mixture's distribution is the one PPO decides below; PPO's construction only resets the env)
        mixing = TeacherMixing(env, teacher, None, config.seed, first_env, total_envs)
        # (what PPO's own update reads of rewards and advantages plays no part in a regression)
        super().__init__(mixing, student, replace(config, group_baseline=False, advantage_norm="none"), logger=logger)
        if self.distill.loss == "mse" and not isinstance(self.distribution, DiagGaussian):
            raise ValueError(f"algo.loss=mse regresses a Gaussian's means; this student's actions are a "
                             f"{self.distribution}: use algo.loss=kl")
        if self.distill.token_dropout:  # (refused here, before a round is collected, rather than at its regression)
            why = None
            if self.recurrent:
                why = "is recurrent"
            elif not callable(getattr(student, "hiding", None)):
                why = "has no tokens to hide"
            elif isinstance(self.obs, Mapping):
                why = f"reads observation groups {sorted(self.obs)}"
            if why:
                raise ValueError(f"algo.token_dropout hides voxels from a feed-forward voxel-token student's attention "
                                 f"(control.controller=attention or attention_hyper) over one observation tensor; "
                                 f"{type(student).__name__} {why}: set algo.token_dropout=0")
        mixing.distribution = self.distribution
        self.teacher = teacher
        self.dataset: dict[str, Any] = {}
        """Per environment: ``obs [N, K, ...]``, the teacher's ``params`` (each ``[N, K, ...]``) and ``value
        [N, K]`` (empty before the first round)."""
        self.filled = 0
        """Samples the dataset holds per environment (K)."""

    def train_epoch(self) -> dict[str, float]:
        """One DAgger round: collect with the mixture policy, label, aggregate, regress."""
        mixing = self.env
        mixing.beta, mixing.step_count, mixing.mixed = (self.distill.beta_at(self.epoch),
                                                        self.global_step // max(self.num_envs, 1), 0.0)
        mixing.resume(self.obs)
        stats = super().train_epoch()
        stats.update(beta=mixing.beta, teacher_steps=mixing.mixed / self.config.rollout_steps)
        return stats

    def update(self) -> dict[str, float]:
        """Label the rollout's observations, add them to the dataset, then ``num_sgd_iter`` shuffled passes of
        minibatch Adam steps on the regression (:func:`distill_loss`): on single samples, or a recurrent student's
        on sequences (:meth:`_regress_sequences`)."""
        self._aggregate(*self._labels())
        for group in self.optimizer.param_groups:
            group["lr"] = self.current_lr()
        totals, steps = self._regress_sequences() if self.recurrent else self._regress_samples()
        means = (self.dp.sum_(totals) / max(steps, 1)).tolist()
        return {"distill_loss": means[0], "distill_kl": means[1], "distill_action_mse": means[2],
                "distill_value_loss": means[3], "dataset_samples": float(self.filled * self.num_envs),
                "lr": self.current_lr()}

    def _regress_samples(self) -> tuple[torch.Tensor, int]:
        """A feed-forward student's passes. Minibatches are drawn from the global dataset (``K · N`` samples,
        sample ``g = k·N + n``) as PPO draws them from its batch: data-parallel, each rank computes the samples it
        holds and the gradients are summed. Returns the statistics' sums ``[4]`` and the number of steps."""
        cfg, dp, flat = self.config, self.dp, self.flat
        obs, params, value = self._flat_dataset()
        size = self.filled * self.num_envs
        minibatch = min(cfg.sgd_minibatch_size, size)

        def reduce(x: torch.Tensor) -> torch.Tensor:
            return dp.minibatch_mean(x, minibatch)

        totals, steps = torch.zeros(4, device=self.device), cfg.num_sgd_iter * (size // minibatch)
        self.policy.train()
        for _ in range(cfg.num_sgd_iter):
            order = torch.randperm(size, generator=self.generator, device=self.device)
            for i in range(size // minibatch):
                draws = (self._elements(minibatch), *self._hidden_cells(minibatch, obs))
                idx, g, *hidden = dp.local_share(order[i * minibatch: (i + 1) * minibatch], *draws)
                flat.zero_grad()
                if idx.numel():  # (a rank may hold none of a minibatch; it then adds zero gradients)
                    batch, labels = self._turned(obs, params, idx, g)
                    with self.policy.hiding(hidden[0]) if hidden else nullcontext():
                        student = tuple(self.policy(batch))
                    loss, stats = distill_loss(student, labels, value.index_select(0, idx), self.distribution,
                                               self.distill.loss, cfg.vf_loss_coeff, reduce)
                    loss.backward()
                    totals += stats
                self._step(flat)
        return totals, steps

    def _regress_sequences(self) -> tuple[torch.Tensor, int]:
        """A recurrent student's passes (DAgger over sequences): each env's K stored steps cut into chunks of
        ``sequence_length`` (:meth:`_sequences`), ``max(1, sgd_minibatch_size // sequence_length)`` chunks a
        minibatch, each run from the student's state at its first step (truncated BPTT), the loss averaged over the
        steps that count. A chunk's symmetry element (``algo.symmetry``) turns all its steps alike: a turned
        episode. Data-parallel, sequences are split between ranks whole (``dp.local_sequences``), as PPO's are."""
        cfg, dp, flat = self.config, self.dp, self.flat
        seq = self._sequences()
        length, sequences = seq.counted.shape  # (global)
        per = min(sequences, max(1, cfg.sgd_minibatch_size // length))
        totals, steps = torch.zeros(4, device=self.device), cfg.num_sgd_iter * (sequences // per)
        self.policy.train()
        for _ in range(cfg.num_sgd_iter):
            order = torch.randperm(sequences, generator=self.generator, device=self.device)
            for i in range(sequences // per):
                idx = order[i * per: (i + 1) * per]
                count, g = seq.counted[:, idx].sum().clamp_min(1), self._elements(per)
                local, mine = dp.local_sequences(idx)
                flat.zero_grad()
                if local.numel():  # (a rank may hold none of a minibatch; it then adds zero gradients)
                    g = (g if mine is None else g[mine]).repeat(length)  # time-major: step t of chunk j is t·S + j
                    loss, stats = self._sequence_loss(seq, local, g, count)
                    loss.backward()
                    totals += stats
                self._step(flat)
        return totals, steps

    def _sequence_loss(self, seq: _Sequences, local: torch.Tensor, g: torch.Tensor, count: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`distill_loss` on this rank's chunks ``local`` of a minibatch, each step's element ``g [L·S]``,
        the means over the minibatch's ``count`` counted steps (every rank's)."""
        length = seq.mask.shape[0]

        def steps_of(x: torch.Tensor) -> torch.Tensor:  # [L, C·n, ...] -> this minibatch's [L·S, ...]
            return x[:, local].reshape(length * local.numel(), *x.shape[2:])

        obs, labels = self._turn(obs_map(steps_of, seq.obs), tuple(steps_of(p) for p in seq.params), g)
        obs = obs_map(lambda x: x.reshape(length, local.numel(), *x.shape[1:]), obs)
        *params, value, _ = self.policy(obs, tuple(s[local] for s in seq.state), seq.starts[:, local])
        student = (*(p.reshape(-1, p.shape[-1]) for p in params), value.reshape(-1))
        return distill_loss(student, labels, steps_of(seq.value), self.distribution, self.distill.loss,
                            self.config.vf_loss_coeff, masked_mean(steps_of(seq.mask), count.to(value.dtype)))

    @torch.no_grad()
    def _sequences(self) -> _Sequences:
        """The dataset as chunks of ``L = min(sequence_length, K)`` steps per env (:class:`_Sequences`). A step
        counts where the student's memory of it is known — at or after the env's first episode start in the
        dataset (the rounds before it were dropped) — and the env did not only reset there. Each chunk starts from
        the state the student, as it is now, reaches over the dataset from that first start: one pass without
        gradients, skipped where every chunk begins an episode (the state is then reset)."""
        d, dp = self.dataset, self.dp
        k = self.filled
        length = min(self.config.sequence_length, k)
        chunks = -(-k // length)

        def cut(x: torch.Tensor) -> torch.Tensor:  # [N, K, ...] -> [L, C·N, ...] (sequence c·N + n)
            return chunked(x.transpose(0, 1), length)

        starts = d["starts"]  # [N, K]
        mask = (starts.long().cummax(1).values.bool() & d["valid"])
        state = self.policy.initial_state(starts.shape[0])
        states = [state] * chunks
        if not bool(starts[:, ::length].all()):  # some chunk begins mid-episode: run the student up to it
            obs = obs_map(lambda x: x.transpose(0, 1), d["obs"])  # [K, N, ...]
            for c in range(1, chunks):
                window = slice((c - 1) * length, c * length)
                *_, state = self.policy(obs_map(lambda x, w=window: x[w], obs), state, starts.T[window])
                states[c] = state
        return _Sequences(obs=obs_map(cut, d["obs"]), params=[cut(p) for p in d["params"]], value=cut(d["value"]),
                          starts=cut(starts), mask=cut(mask),
                          state=tuple(torch.cat([st[j] for st in states]) for j in range(len(state))),
                          counted=cut(dp.gather_envs(mask, dim=0)))

    def _elements(self, minibatch: int) -> torch.Tensor:
        """The symmetry's element for each sample of a global minibatch ``[minibatch]`` (all 0 without one); drawn
        for the whole minibatch from the shared generator, so every rank and a resumed run draw the same."""
        if self.symmetry is None:
            return torch.zeros(minibatch, dtype=torch.long, device=self.device)
        return torch.randint(self.symmetry.size, (minibatch,), generator=self.generator, device=self.device)

    def _hidden_cells(self, minibatch: int, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Token dropout's hidden cells for each sample of a global minibatch of the dataset's observations ``obs
        [K·n, C, Bx, By, Bz]``: ``([minibatch, Bx·By·Bz] bool,)`` (``()`` without it: no draw, so a run without it
        draws as before; a single observation tensor, as ``__init__`` checked); from the shared generator, as
        :meth:`_elements`."""
        p = self.distill.token_dropout
        if not p:
            return ()
        return (torch.rand(minibatch, math.prod(obs.shape[2:]), generator=self.generator, device=self.device) < p,)

    def _turned(self, obs: Observation, params: list[torch.Tensor], idx: torch.Tensor, g: torch.Tensor
                ) -> tuple[Observation, tuple[torch.Tensor, ...]]:
        """The samples ``idx`` of the dataset and their labels, each turned by its element ``g`` (the value, a
        scalar of the task, is unchanged)."""
        return self._turn(obs_map(lambda x: x.index_select(0, idx), obs), tuple(p.index_select(0, idx) for p in params), g)

    def _turn(self, batch: Observation, labels: tuple[torch.Tensor, ...], g: torch.Tensor
              ) -> tuple[Observation, tuple[torch.Tensor, ...]]:
        """Samples ``[M, ...]`` and their labels, each turned by its element ``g [M]``."""
        if self.symmetry is None:
            return batch, labels
        if isinstance(batch, Mapping):
            raise ValueError("algo.symmetry turns a single observation tensor; this env observes groups "
                             f"{sorted(batch)}")
        return self.symmetry.observations(batch, g), tuple(self.symmetry.cells(p, g) for p in labels)

    def _flat_dataset(self) -> tuple[Observation, list[torch.Tensor], torch.Tensor]:
        """The dataset's samples in the order ``k·n_local + n`` (``[K·n_local, ...]``), as ``local_share`` indexes
        a rollout."""
        def flat(x: torch.Tensor) -> torch.Tensor:
            return x.transpose(0, 1).reshape(-1, *x.shape[2:])

        d = self.dataset
        return obs_map(flat, d["obs"]), [flat(p) for p in d["params"]], flat(d["value"])

    @torch.no_grad()
    def _labels(self) -> tuple[Observation, list[torch.Tensor], torch.Tensor]:
        """The rollout's observations ``[N, T, ...]`` and the teacher's params and value on them (``[N, T, ...]``)."""
        buf = self.rollout
        t, n = buf.rewards.shape
        flat = obs_map(lambda x: x.reshape(t * n, *x.shape[2:]), buf.obs)
        envs = torch.arange(n, device=self.device).repeat(t)
        *params, value = self.teacher(flat, envs)
        value = value if value is not None else torch.full((t * n,), float("nan"), device=self.device)

        def per_env(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(t, n, *x.shape[1:]).transpose(0, 1).contiguous()

        return obs_map(per_env, flat), [per_env(p.to(self.device)) for p in params], per_env(value.to(self.device))

    def _aggregate(self, obs: Observation, params: list[torch.Tensor], value: torch.Tensor) -> None:
        """Append a round's samples ``[N, T, ...]``; keep the last ``buffer`` rounds' (``K = buffer · T``)."""
        capacity = self.distill.buffer * self.config.rollout_steps
        d, first = self.dataset, not self.dataset

        def keep(old: torch.Tensor | None, new: torch.Tensor) -> torch.Tensor:
            return (new if old is None else torch.cat([old, new], 1))[:, -capacity:]

        if isinstance(obs, Mapping):
            d["obs"] = {k: keep(None if first else d["obs"][k], v) for k, v in obs.items()}
        else:
            d["obs"] = keep(None if first else d["obs"], obs)
        d["params"] = [keep(None if first else d["params"][i], p) for i, p in enumerate(params)]
        d["value"] = keep(None if first else d["value"], value)
        if self.recurrent:  # where an episode begins, and where the env only reset (no transition), per step
            for name, x in (("starts", self.rollout.episode_starts), ("valid", self.rollout.valid)):
                d[name] = keep(None if first else d[name], x.transpose(0, 1).contiguous())
        self.filled = int(d["value"].shape[1])

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        d = self.dataset
        data = {"obs": d["obs"], "value": d["value"], **{k: d[k] for k in STEP_FLAGS if k in d},
                **{f"params_{i}": p for i, p in enumerate(d["params"])}} if d else {}
        state["distill"] = self.dp.gather_state({"filled": self.filled, PER_ENV: data})
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        part = self.dp.shard_state(state["distill"])
        self.filled = int(part["filled"])
        data = part[PER_ENV]
        self.dataset = {} if not data else {
            "obs": obs_map(lambda x: x.to(self.device), data["obs"]), "value": data["value"].to(self.device),
            "params": [data[f"params_{i}"].to(self.device) for i in range(sum(k.startswith("params_") for k in data))],
            **{k: data[k].to(self.device) for k in STEP_FLAGS if k in data}}
        if self.recurrent and self.dataset and not all(k in self.dataset for k in STEP_FLAGS):
            raise ValueError("this checkpoint's dataset was a feed-forward student's: it has no episode starts for "
                             "a recurrent student's sequences (resume it with the student it was saved with)")


def bank_from_checkpoint(payload: Mapping[str, Any], source: str) -> TeacherBank:
    """The teacher bank of a teacher run's checkpoint (``control.teachers`` > 0), weights loaded."""
    if not str(payload.get("policy_class", "")).endswith(":TeacherBank"):
        raise ValueError(f"algo.teacher={source}: not a teacher run's checkpoint (its policy is "
                         f"{payload.get('policy_class')!r}, not a TeacherBank: train one with control.teachers=M)")
    bank = TeacherBank(**payload["policy_kwargs"])
    bank.load_state_dict(payload["ppo"]["policy"])
    return bank


__all__ = ["LOSSES", "BankTeacher", "ChosenTeacher", "DistillConfig", "Distillation", "Symmetry", "Teacher", "TeacherMixing",
           "bank_from_checkpoint", "distill_loss"]
