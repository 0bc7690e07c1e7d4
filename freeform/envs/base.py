"""The protocols the rest of freeform relies on: a batched environment (what PPO consumes) and a task (what a
design is scored by). The trainer checks its env and task against them when it builds a run."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import torch


@runtime_checkable
class VecEnv(Protocol):
    """A batch of ``num_envs`` environments stepped together, on one torch device.

    ``reset(seed)`` returns the first observations ``[num_envs, *observation_shape]`` (or a dict of such tensors,
    with ``observation_shape`` a dict of shapes: an env whose observations have named parts, for a policy that
    reads them by name).
    ``step(actions [num_envs, action_dim])`` (float, or int64 indices for an env whose ``action_distribution`` is
    discrete) returns ``(obs, reward [num_envs] float32, done [num_envs] bool, info)``,
    new tensors each step: PPO keeps them, and the ``actions`` it passed, until its rollout ends, so an env must
    not write into a tensor it returned nor into ``actions``.
    When ``done[i]`` the environment resets itself: ``obs[i]`` is the first observation of the next episode, and
    whatever describes the finished episode travels in ``info``: every tensor in ``info`` is per environment,
    ``[num_envs, ...]`` (a data-parallel run gathers them over ranks for its records).

    Optional attribute: ``action_distribution``, the ``freeform.distributions.ActionDistribution`` its actions
    need (a categorical for discrete actions, a masked Gaussian for a control env; none: a Gaussian over
    ``action_dim`` floats).

    Optional ``info`` keys PPO reads (the design env sets none: its episodes end only by termination, at step T):

    - ``truncated [num_envs]`` bool (⊆ ``done``): a time limit cut the episode; it was not terminated. PPO then
      bootstraps the episode's return with V(``final_obs``); a terminated episode gets no bootstrap.
    - ``final_obs [num_envs, *observation_shape]``: the last observation of the episodes that ended at this step
      (rows of the other envs are ignored); needed whenever some ``truncated`` is set.
    - ``autoreset [num_envs]`` bool: this step only reset the env (Gymnasium's next-step autoreset: the action was
      ignored, the reward is 0, ``obs`` is the new episode's first observation). PPO keeps such samples out of the
      loss and the episode lengths. An env using it returns, at the step that ends an episode, that episode's last
      observation as ``obs``.
    """

    num_envs: int
    observation_shape: tuple[int, ...]
    action_dim: int
    device: torch.device

    def reset(self, seed: int | None = None) -> torch.Tensor: ...

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]: ...


@runtime_checkable
class StatefulVecEnv(VecEnv, Protocol):
    """A :class:`VecEnv` that can be checkpointed mid-episode (optional: PPO saves the state of envs that have it).

    ``state_dict()`` names its per-environment tensors: they sit under a ``"per_env"`` key (each ``[num_envs,
    ...]``), so that a data-parallel checkpoint concatenates exactly those over ranks and nothing else.
    """

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


@runtime_checkable
class Task(Protocol):
    """What a design is scored by: one reward per final grid.

    ``reward`` may also take a keyword ``bodies=`` (the grids' largest components, same shape): ``DesignEnv`` then
    passes the bodies it has already computed instead of labelling the grids twice.
    """

    def reward(self, final_grids: torch.Tensor) -> torch.Tensor:
        """``final_grids``: uint8 ``[N, ρ, ρ, ρ]`` material indices -> float32 ``[N]``."""
        ...


@runtime_checkable
class ReportsStats(Protocol):
    """A task that reports figures of its last ``reward`` call (TensorBoard tag -> value, e.g. the simulation's
    ``perf/sim_seconds``); the trainer logs them every epoch (summed over ranks; times by max)."""

    stats: Mapping[str, float]


@runtime_checkable
class ReportsPlacement(Protocol):
    """A task that may place a body other than as designed (``placements`` yaw rotations,
    ``freeform.envs.tasks.SimulatedTask``): ``yaw [N]`` int, each body's placement in quarter turns after the last
    ``reward`` call. The design env passes it on as ``info["yaw"]``; records and renders keep it."""

    yaw: torch.Tensor
