"""The batched-environment protocol that every freeform environment follows (and that PPO consumes)."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch


@runtime_checkable
class VecEnv(Protocol):
    """A batch of ``num_envs`` environments stepped together, on one torch device.

    ``reset(seed)`` returns the first observations ``[num_envs, *observation_shape]``.
    ``step(actions [num_envs, action_dim])`` returns ``(obs, reward [num_envs] float32, done [num_envs] bool, info)``.
    When ``done[i]`` the environment resets itself: ``obs[i]`` is the first observation of the next episode, and
    whatever describes the finished episode travels in ``info``.
    """

    num_envs: int
    observation_shape: tuple[int, ...]
    action_dim: int
    device: torch.device

    def reset(self, seed: int | None = None) -> torch.Tensor: ...

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]: ...


class Task(Protocol):
    """What a design is scored by: one reward per final grid."""

    def reward(self, final_grids: torch.Tensor) -> torch.Tensor:
        """``final_grids``: uint8 ``[N, ρ, ρ, ρ]`` material indices -> float32 ``[N]``."""
        ...
