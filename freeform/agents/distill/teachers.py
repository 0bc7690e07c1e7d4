"""A bank of teachers: M controllers of one kind, each with its own weights, trained and run as one batch (issue 56).

Per-body control learns where one controller for many bodies does not (``docs/control.md``): a body's own PPO
controller moves it several times what the population controller does. The bank trains one such controller per
body in one process, and is what a student is distilled from (``freeform.agents.distill``).

The weights are the template controller's, stacked: parameter ``p`` of shape ``S`` becomes ``[M, *S]``, so that
the optimiser's per-element moments are each teacher's own and the loss's sum over samples splits into each
teacher's loss. A forward pass sorts its samples by teacher, pads each teacher's block to the largest one, and runs
the template once under ``torch.func.vmap`` over the teachers (a convolution of M weight sets becomes one grouped
convolution): no Python loop over teachers, and a teacher's outputs are what its weights give alone (the batch
invariance test). The observation names each sample's teacher: the group ``"teacher"`` (int64 ``[N]``), which
:class:`TeacherIndex` adds to any ``VecEnv``'s observation; the other groups are the template's input
(``"policy"`` alone, or ``"policy"`` and ``"critic"`` for a controller with a privileged critic).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from typing import Any

import torch
import torch.nn as nn
from torch.func import functional_call, stack_module_state, vmap

from freeform.agents.networks.observation_groups import POLICY
from freeform.agents.networks.recurrent import RecurrentPolicy

TEACHER = "teacher"
"""The observation group naming each sample's teacher: int64 ``[N]`` in ``0 … M−1``."""


def _key(name: str) -> str:
    return name.replace(".", "__")


class TeacherBank(nn.Module):
    """``teachers`` controllers of kind ``kind`` (a key of ``freeform.agents.networks.controllers.CONTROLLERS``, built from
    ``controller``, its ``init_kwargs``; with ``critic_dim`` each inside a ``PrivilegedCritic`` whose MLP is
    ``critic_hidden`` wide), each its own
    weights. ``forward({"teacher": [N] int64, "policy": [N, ...], ...})`` returns what each sample's teacher returns
    on it: ``(*params [N, ...], value [N])``. :meth:`from_template` starts every teacher from one controller."""

    def __init__(self, teachers: int, kind: str, controller: dict[str, Any], critic_dim: int | None = None,
                 critic_hidden: int = 64) -> None:
        super().__init__()
        from freeform.agents.networks.controllers import CONTROLLERS

        if not isinstance(teachers, int) or teachers < 1:
            raise ValueError(f"teachers must be a positive int, got {teachers!r}")
        if kind not in CONTROLLERS:
            raise ValueError(f"controller kind must be one of {list(CONTROLLERS)}, got {kind!r}")
        if issubclass(CONTROLLERS[kind], RecurrentPolicy):
            raise ValueError(f"controller {kind!r} is recurrent; a teacher bank holds feed-forward controllers")
        self.teachers = teachers
        self.init_kwargs = {"teachers": teachers, "kind": kind, "controller": dict(controller),
                            "critic_dim": critic_dim, "critic_hidden": critic_hidden}
        self.template = self._new_controller()
        stacked, _ = stack_module_state([self.template] * teachers)
        self.stacked = nn.ParameterDict({_key(k): nn.Parameter(v.detach().clone()) for k, v in stacked.items()})
        self._names = {_key(k): k for k in stacked}
        for name, p in list(self.template.named_parameters()):  # (the template lends its structure; the weights
            owner, _, leaf = name.rpartition(".")                # are the bank's: its own become constants)
            module = self.template.get_submodule(owner)
            delattr(module, leaf)
            module.register_buffer(leaf, p.detach(), persistent=False)
        self.distribution = getattr(self.template, "distribution", None)
        self.fits_any_box = getattr(self.template, "fits_any_box", False)
        self.padding_invariant = getattr(self.template, "padding_invariant", False)

    def _new_controller(self) -> nn.Module:
        """A fresh controller of the teachers' kind (its own weights, untrained)."""
        from freeform.agents.networks import rebuild
        from freeform.agents.networks.controllers import CONTROLLERS, PrivilegedCritic

        k = self.init_kwargs
        if k["critic_dim"] is None:
            return rebuild(CONTROLLERS[k["kind"]], k["controller"])
        return PrivilegedCritic(k["kind"], k["controller"], k["critic_dim"], k["critic_hidden"])

    @classmethod
    def from_template(cls, template: nn.Module, teachers: int) -> TeacherBank:
        """A bank whose every teacher starts as ``template`` (a registered controller, or a ``PrivilegedCritic``)."""
        from freeform.agents.networks.controllers import PrivilegedCritic, controller_kind

        if isinstance(template, PrivilegedCritic):
            kwargs = template.init_kwargs
            bank = cls(teachers, kwargs["kind"], kwargs["controller"], kwargs["critic_dim"], kwargs["hidden"])
        else:
            bank = cls(teachers, controller_kind(template), template.init_kwargs)
        state = template.state_dict()
        for m in range(teachers):
            bank.load_member(m, state)
        return bank

    @classmethod
    def concatenate(cls, banks: list[TeacherBank]) -> TeacherBank:
        """One bank of every teacher of ``banks``, in order (teacher j of the second is teacher M₁ + j): banks
        trained apart — on other bodies, in other runs or jobs — taught together. They must hold the same kind of
        controller built alike (refused naming the settings that differ) — for a kind that the padding changes
        (``conv``, ``mlp``), built for the same box; the others' pool is built for the box that holds every bank's."""
        if not banks:
            raise ValueError("concatenate needs at least one TeacherBank")

        def built(bank: TeacherBank) -> dict[str, Any]:  # (a kind the padding does not change: the box is no
            k = {key: v for key, v in bank.init_kwargs.items() if key != "teachers"}  # weight, and no input)
            return {**k, "controller": {c: v for c, v in k["controller"].items()
                                        if not (c == "box" and bank.padding_invariant)}}

        first = built(banks[0])
        for i, bank in enumerate(banks[1:], 1):
            other = built(bank)
            if other != first:
                differ = [k for k in {**first, **other} if first.get(k) != other.get(k)]
                if "controller" in differ:
                    mine, theirs = first["controller"], other["controller"]
                    differ += [f"controller.{k}" for k in {**mine, **theirs} if mine.get(k) != theirs.get(k)]
                raise ValueError(f"bank {i} holds other controllers than bank 0 (they differ in {differ}): only "
                                 "teachers of one kind and width, built alike, join one bank")
        if banks[0].padding_invariant:  # (built for the box that holds every bank's bodies)
            boxes = [b.init_kwargs["controller"]["box"] for b in banks]
            first["controller"]["box"] = tuple(max(side) for side in zip(*boxes, strict=True))
        out = cls(sum(b.teachers for b in banks), **first)
        with torch.no_grad():
            for k, p in out.stacked.items():
                p.copy_(torch.cat([b.stacked[k].to(p.device) for b in banks]))
        return out

    def select(self, teachers: Sequence[int]) -> TeacherBank:
        """A bank of the teachers ``teachers`` of this one, in that order (teacher j of it is ``teachers[j]`` here):
        the teachers of the bodies an expert won, say (``freeform.run.teacher_runs``'s ``--teachers``)."""
        chosen = [int(t) for t in teachers]
        if not chosen or not all(0 <= t < self.teachers for t in chosen):
            raise ValueError(f"teachers to select must be a non-empty list of 0 … {self.teachers - 1}, got {chosen}")
        out = type(self)(len(chosen), **{k: v for k, v in self.init_kwargs.items() if k != "teachers"})
        index = torch.tensor(chosen, device=next(iter(self.stacked.values())).device)
        with torch.no_grad():
            for k, p in out.stacked.items():
                p.copy_(self.stacked[k].index_select(0, index).to(p.device))
        return out

    def member_state(self, teacher: int) -> dict[str, torch.Tensor]:
        """Teacher ``teacher``'s weights, named as in the template's ``state_dict``."""
        if not 0 <= teacher < self.teachers:
            raise ValueError(f"teacher must be in 0 … {self.teachers - 1}, got {teacher}")
        return {self._names[k]: v[teacher].detach().clone() for k, v in self.stacked.items()}

    def mean_state(self) -> dict[str, torch.Tensor]:
        """The teachers' weights averaged, named as in the template's ``state_dict`` (a bank started from one
        controller: the Reptile step's target, ``freeform.run.teacher_runs.reptile_step``)."""
        return {self._names[k]: v.detach().mean(0) for k, v in self.stacked.items()}

    def member(self, teacher: int) -> nn.Module:
        """A controller (the template's class) holding teacher ``teacher``'s weights: runs alone what the bank runs
        for that teacher."""
        alone = self._new_controller().to(next(iter(self.stacked.values())).device)
        alone.load_state_dict(self.member_state(teacher))
        return alone

    def load_member(self, teacher: int, state: Mapping[str, torch.Tensor]) -> None:
        """Set teacher ``teacher``'s weights from a template ``state_dict`` (e.g. a body's controller trained
        alone)."""
        with torch.no_grad():
            for k, p in self.stacked.items():
                p[teacher].copy_(state[self._names[k]])

    def forward(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """``obs``: the groups, ``"teacher"`` int64 ``[N]`` among them → each sample's teacher's outputs
        ``(*params, value)``, each ``[N, ...]``."""
        if not isinstance(obs, Mapping) or TEACHER not in obs:
            raise ValueError(f"a TeacherBank reads the observation group {TEACHER!r} (each sample's teacher: "
                             "TeacherIndex adds it)")
        teacher = obs[TEACHER].long().reshape(-1)
        inputs = {k: v for k, v in obs.items() if k != TEACHER}
        inputs[POLICY] = self._own_channels(inputs[POLICY])
        slots, valid = self._slots(teacher)
        blocks = {k: v[slots] for k, v in inputs.items()}  # [M, W, ...]
        x = blocks[POLICY] if set(blocks) == {POLICY} else blocks
        params = {self._names[k]: v for k, v in self.stacked.items()}

        def one(p: dict[str, torch.Tensor], block: Any) -> tuple[torch.Tensor, ...]:
            return tuple(functional_call(self.template, p, (block,)))

        with ExitStack() as stack:
            for module in self.template.modules():  # (shapes that depend on the data fixed to this batch's)
                if hasattr(module, "fixed_shapes"):
                    stack.enter_context(module.fixed_shapes(inputs[POLICY]))
            outs = vmap(one)(params, x)
        back = torch.argsort(slots[valid])  # (sample i sits at row back[i] of the valid slots)
        return tuple(out[valid][back] for out in outs)

    def _own_channels(self, obs: torch.Tensor) -> torch.Tensor:
        """The channels the teachers were built for, the first ``C`` of ``obs [N, C', ...]``: a student's env may
        append channels its teachers never saw (``control.response``), never remove any."""
        channels = self.init_kwargs["controller"].get("channels")
        if channels is None or obs.dim() < 2 or obs.shape[1] == channels:
            return obs
        if obs.shape[1] < channels:
            raise ValueError(f"the teachers read {channels} observation channels and this env gives {obs.shape[1]}: "
                             "run them on an env with their run's channels (control.residual, control.response)")
        return obs[:, :channels]

    def _slots(self, teacher: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``slots [M, W]``: the samples of each teacher in order, each block padded to the largest one (W samples)
        with the teacher's first sample (or sample 0 for a teacher with none: those rows are computed, then
        dropped); ``valid [M, W]``: the slots that are samples of their own."""
        n = teacher.numel()
        if n and (int(teacher.min()) < 0 or int(teacher.max()) >= self.teachers):
            raise ValueError(f"teacher indices must be in 0 … {self.teachers - 1}, got {int(teacher.min())} … "
                             f"{int(teacher.max())}")
        order = torch.argsort(teacher, stable=True)
        counts = torch.bincount(teacher, minlength=self.teachers)
        width = max(1, int(counts.max()))
        starts = torch.cumsum(counts, 0) - counts
        j = torch.arange(width, device=teacher.device)
        valid = j[None, :] < counts[:, None]
        pos = starts[:, None] + torch.minimum(j[None, :], (counts[:, None] - 1).clamp_min(0))
        return order[pos.clamp(0, max(n - 1, 0))], valid


class TeacherIndex:
    """A ``VecEnv`` whose observation also names each environment's teacher: ``{"teacher": teacher [N] int64,
    "policy": the env's observation}`` (an env observing groups keeps them, and gains ``"teacher"``).

    env: any ``VecEnv``; teacher: int64 ``[num_envs]`` in ``0 … M−1`` (a control env of M bodies repeated in turn:
    ``arange(N) % M``). ``reward_groups`` is ``teacher``, so that PPO's ``group_baseline`` and ``advantage_norm=
    "group"`` judge each teacher's samples among its own; everything else is the env's.
    """

    def __init__(self, env: Any, teacher: torch.Tensor) -> None:
        teacher = torch.as_tensor(teacher, dtype=torch.long).reshape(-1)
        if teacher.numel() != env.num_envs:
            raise ValueError(f"teacher must name one teacher per environment ({env.num_envs}), got {teacher.numel()}")
        if teacher.numel() and int(teacher.min()) < 0:
            raise ValueError("teacher indices must be >= 0")
        self.env = env
        self.teacher = teacher.to(env.device)
        self.reward_groups = self.teacher
        self.num_envs, self.action_dim, self.device = env.num_envs, env.action_dim, env.device
        shape = env.observation_shape
        groups = dict(shape) if isinstance(shape, Mapping) else {POLICY: tuple(shape)}
        self.observation_shape = {TEACHER: (), **groups}

    def __getattr__(self, name: str) -> Any:  # (everything else is the env's: its bodies, box, distribution ...)
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def observe(self, obs: Any) -> dict[str, torch.Tensor]:
        """The env's observation with the ``"teacher"`` group."""
        groups = dict(obs) if isinstance(obs, Mapping) else {POLICY: obs}
        return {TEACHER: self.teacher.clone(), **groups}

    def reset(self, seed: int | None = None) -> dict[str, torch.Tensor]:
        return self.observe(self.env.reset(seed))

    def record(self, act: Any, robot: int = 0, every: int | None = None) -> Any:
        """The env's ``record`` (a control env's episode for looking at) under ``act``, which reads the groups."""
        return self.env.record(lambda obs: act(self.observe(obs)), robot, every)

    def step(self, actions: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, dict[str, Any]]:
        obs, reward, done, info = self.env.step(actions)
        if "final_obs" in info:
            info = {**info, "final_obs": self.observe(info["final_obs"])}
        return self.observe(obs), reward, done, info


__all__ = ["TEACHER", "TeacherBank", "TeacherIndex"]
