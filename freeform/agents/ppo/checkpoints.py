"""PPO's state and checkpoints: ``state_dict``/``load_state_dict`` (everything to continue exactly; what is per
environment under ``per_env``), the self-describing ``checkpoint``, ``save`` and ``PPO.load``, as a part of the
``PPO`` class (``ppo.py``); and how a checkpoint names a policy class."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Self

import torch
import torch.nn as nn

from freeform.agents import distributed
from freeform.agents.distributed import PER_ENV, Collectives
from freeform.agents.networks import Rebuildable, rebuild
from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.flat_params import FlatParameters
from freeform.agents.ppo.graphed import GraphedMinibatchStep
from freeform.agents.ppo.normalization import RunningMeanStd
from freeform.agents.ppo.rollout import Observation, obs_first, obs_map, obs_shapes
from freeform.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from freeform.envs.base import VecEnv
from freeform.records import EpisodeCollector

if TYPE_CHECKING:  # (the TensorBoard writer is not imported with PPO)
    from freeform.logger import ScalarSink


class Checkpoints:
    """The state half of :class:`freeform.agents.PPO`: what it reads and writes of the PPO is declared here."""

    config: PPOConfig
    env: VecEnv
    policy: nn.Module
    dp: Collectives
    device: torch.device
    generator: torch.Generator
    flat: FlatParameters
    optimizer: torch.optim.Adam
    num_envs: int
    epoch: int
    global_step: int
    kl_coeff: float
    obs: Observation
    episode_return: torch.Tensor
    episode_length: torch.Tensor
    recent_returns: torch.Tensor
    recent_lengths: torch.Tensor
    obs_rms: RunningMeanStd | dict[str, RunningMeanStd] | None
    return_rms: RunningMeanStd | None
    discounted_return: torch.Tensor
    _collector: EpisodeCollector
    _collected: int
    _graphed: GraphedMinibatchStep | None
    recurrent: bool
    policy_state: tuple[torch.Tensor, ...]
    episode_start: torch.Tensor
    _here: Callable[[Observation], Observation]  # (RolloutCollection)
    _lr_value: Callable[[float], float | torch.Tensor]  # (MinibatchUpdate)

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
            "recent_episodes": {"returns": self.recent_returns, "lengths": self.recent_lengths},  # global
        }
        if self.recurrent:  # the state after the last observation, and whether the next one starts an episode
            state[PER_ENV].update({f"policy_state_{i}": s for i, s in enumerate(self.policy_state)},
                                  episode_start=self.episode_start)
        if isinstance(self.obs_rms, dict):  # per part of a dict observation
            state["obs_rms"] = {k: rms.state_dict() for k, rms in self.obs_rms.items()}
        elif self.obs_rms is not None:
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
        recent = state.get("recent_episodes")  # (absent from checkpoints before PPOConfig.stats_window: none yet)
        self.recent_returns = recent["returns"].float().cpu() if recent else torch.zeros(0)
        self.recent_lengths = recent["lengths"].long().cpu() if recent else torch.zeros(0, dtype=torch.int64)
        if self.recurrent:
            saved = sorted(k for k in per_env if k.startswith("policy_state_"))
            if len(saved) != len(self.policy_state):
                raise ValueError(f"the state holds {len(saved)} recurrent state tensors, and this policy has "
                                 f"{len(self.policy_state)}")
            self.policy_state = tuple(per_env[f"policy_state_{i}"].to(self.device) for i in range(len(saved)))
            self.episode_start = per_env["episode_start"].to(self.device, torch.bool)
        for name, rms in (("obs_rms", self.obs_rms), ("return_rms", self.return_rms)):
            if rms is not None:
                if name not in state:
                    raise ValueError(f"the config normalises ({name}) but the state holds no {name} statistics")
                if isinstance(rms, dict):
                    if set(rms) != set(state[name]):
                        raise ValueError(f"the state's {name} has parts {sorted(state[name])}, this run {sorted(rms)}")
                    for key, part in rms.items():
                        part.load_state_dict(state[name][key])
                else:
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
    ) -> Self:
        """Rebuild a PPO (policy, config, full training state) from a file of :meth:`save` or a run's checkpoint.

        The file names its policy class; it is built only if it is one of freeform's networks or in
        ``policy_classes`` (the caller's own, allowed explicitly): loading never imports what a file names, and the
        file itself is read with ``weights_only`` (no code runs). ``device`` overrides the saved ``config.device``.
        Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file for a corrupt or
        incompatible one.
        """
        payload = load_checkpoint(path)
        known = (*builtin_policies(), *policy_classes)
        allowed = {policy_class_name(c): c for c in known}
        allowed.update(moved_policies(known))
        try:
            name = payload["policy_class"]
            if name not in allowed:
                raise CheckpointError(
                    f"{path}: its policy class {name!r} is not one of freeform's networks; pass "
                    f"policy_classes=[<that class>] to PPO.load to build it (a bank of teachers: "
                    f"policy_classes=[freeform.agents.distill.TeacherBank])"
                )
            policy = rebuild(allowed[name], payload["policy_kwargs"])
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


def policy_class_name(cls: type) -> str:
    """How a checkpoint names a policy class: ``module:qualname``."""
    return f"{cls.__module__}:{cls.__qualname__}"


def builtin_policies() -> tuple[type[nn.Module], ...]:
    """The networks any checkpoint may name (freeform's own: every controller of the registry included). A bank of
    teachers is distillation's (``freeform.agents.distill.TeacherBank``, above PPO): ``policy_classes=[TeacherBank]``."""
    from freeform.agents.networks import GroupedMLPActorCritic, MLPActorCritic, VoxelActorCritic
    from freeform.agents.networks.codesign_network import CodesignActorCritic
    from freeform.agents.networks.controllers import CONTROLLERS, PrivilegedCritic
    from freeform.agents.networks.recurrent import RecurrentActorCritic

    return (VoxelActorCritic, MLPActorCritic, CodesignActorCritic, GroupedMLPActorCritic, RecurrentActorCritic,
            PrivilegedCritic, *CONTROLLERS.values())


MOVED_MODULES = {"freeform.agents.networks": "freeform.agents.networks.base",
                 **{f"freeform.agents.{m}": f"freeform.agents.networks.{m}"
                    for m in ("controllers", "attention_controllers", "codesign_network", "recurrent",
                              "observation_groups")},
                 "freeform.agents.teachers": "freeform.agents.distill.teachers"}
"""Modules whose classes older checkpoints name, and where those classes live since ``agents/`` was laid out by kind
(networks, ppo, distill)."""


def moved_policies(known: Sequence[type[nn.Module]] = ()) -> dict[str, type[nn.Module]]:
    """Names that older checkpoints give classes since moved (``module:qualname`` then → the class now): the classes
    moved between modules, and every builtin policy (and every class of ``known``) under its module's name before
    :data:`MOVED_MODULES`."""
    from freeform.agents.networks.attention_controllers import (
        RecurrentAttentionController,
        VoxelAttentionController,
    )
    from freeform.agents.networks.base import GroupedMLPActorCritic
    from freeform.agents.networks.codesign_network import CodesignActorCritic
    from freeform.agents.networks.controllers import ConvController, MLPController

    earlier = {"controllers:VoxelAttentionController": VoxelAttentionController,
               "controllers:RecurrentAttentionController": RecurrentAttentionController,
               "networks:ConvController": ConvController,
               "networks:MLPController": MLPController,
               "networks:CodesignActorCritic": CodesignActorCritic,
               "observation_groups:GroupedMLPActorCritic": GroupedMLPActorCritic}
    moved = {f"freeform.agents.{name}": cls for name, cls in earlier.items()}
    before = {new: old for old, new in MOVED_MODULES.items()}
    for cls in (*builtin_policies(), *known):
        if cls.__module__ in before:
            moved[f"{before[cls.__module__]}:{cls.__qualname__}"] = cls
    return moved


__all__ = ["Checkpoints", "builtin_policies", "policy_class_name"]
