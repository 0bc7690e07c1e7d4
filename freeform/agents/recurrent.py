"""Recurrent policies: the protocol by which a network declares it has memory, and ``RecurrentActorCritic`` (an
LSTM or GRU, the sizes of SB3-contrib's ``MlpLstmPolicy`` by default).

The protocol (``RecurrentPolicy``): ``initial_state(num_envs)`` gives the state at an episode's start, a tuple of
tensors ``[N, ...]`` (batch first); ``forward(obs [T, N, ...], state, episode_start [T, N]) -> (*params [T, N, P_i],
value [T, N], state)`` runs T steps, where before step t every env with ``episode_start[t]`` restarts from the
initial state (its row of the state multiplied by 0: the initial state is zeros). PPO carries the state across
rollout steps, stores it at every step, and trains on chunks of ``PPOConfig.sequence_length`` steps that start from
the stored state (truncated backpropagation through time). Optionally (``SplitRecurrentPolicy``) the actor runs
alone: the first ``actor_state_size`` tensors of the state are the actor's, and ``action_params(obs, actor_state,
episode_start) -> (params, actor_state)`` — what an exported policy runs.

Shapes: ``T`` steps, ``N`` environments (or sequences), ``H`` the recurrent width, ``L`` its layers.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

State = tuple[torch.Tensor, ...]
"""A recurrent policy's hidden state: tensors ``[N, ...]``, batch first."""


@runtime_checkable
class RecurrentPolicy(Protocol):
    """A policy with memory (module docstring): PPO then carries its state and trains on sequences."""

    def initial_state(self, num_envs: int) -> State: ...

    def __call__(self, obs: torch.Tensor, state: State, episode_start: torch.Tensor) -> tuple[torch.Tensor, ...]: ...


@runtime_checkable
class SplitRecurrentPolicy(RecurrentPolicy, Protocol):
    """A recurrent policy whose actor runs without its critic (an exported policy runs only that)."""

    actor_state_size: int

    def action_params(self, obs: torch.Tensor, actor_state: State, episode_start: torch.Tensor
                      ) -> tuple[tuple[torch.Tensor, ...], State]: ...


__all__ = ["RecurrentPolicy", "SplitRecurrentPolicy", "State"]
