"""Observation groups: a dict observation with the keys ``"policy"`` and ``"critic"`` (rsl_rl's observation groups,
skrl's states). The actor reads only ``"policy"``; the critic reads both — ``"critic"`` holds what only the critic may
see (privileged state: what the sensors lack). PPO normalises each group by its own statistics (``obs_norm``), and an
exported actor (``PPO.export``) takes ``"policy"`` alone.

A Gymnasium env whose observation space is ``Dict({"policy": ..., "critic": ...})`` arrives so through
``freeform.envs.from_gymnasium(..., dict_obs=True)``; :class:`freeform.agents.MLPActorCritic` ``.for_env`` then builds
the grouped network (:class:`GroupedMLPActorCritic`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.distributions import ActionDistribution
from freeform.agents.networks import MLPActorCritic

POLICY = "policy"
"""The actor's group (and the critic's)."""
CRITIC = "critic"
"""The critic's own group: privileged observations."""
GROUPS = (POLICY, CRITIC)


def is_grouped(observation_shape: Any) -> bool:
    """True where an env's ``observation_shape`` is a dict of exactly the two groups."""
    return isinstance(observation_shape, Mapping) and set(observation_shape) == set(GROUPS)


def without_critic(obs: Any) -> Any:
    """What the actor may read of an observation: a dict's parts less the ``"critic"`` group."""
    return {k: v for k, v in obs.items() if k != CRITIC} if isinstance(obs, Mapping) else obs


class GroupedMLPActorCritic(MLPActorCritic):
    """:class:`~freeform.agents.MLPActorCritic` over observation groups: the actor's MLP reads ``obs["policy"]``
    only, the critic's the two groups side by side (``[policy, critic]``, each flattened). Otherwise CleanRL's nets
    as there (orthogonal init, state-independent log σ, any of the discrete heads)."""

    def __init__(self, policy_dim: int, critic_dim: int, action_dim: int | None = None,
                 hidden: tuple[int, ...] | list[int] = (64, 64),
                 distribution: ActionDistribution | dict[str, Any] | None = None) -> None:
        super().__init__(policy_dim, action_dim, hidden, distribution)
        if not isinstance(critic_dim, int) or critic_dim < 1:
            raise ValueError(f"critic_dim must be a positive int, got {critic_dim!r}")
        first = self.critic[0]  # the critic's first layer reads both groups
        self.critic[0] = self._orthogonal(nn.Linear(policy_dim + critic_dim, first.out_features), math.sqrt(2.0))
        self._critic_linears = tuple(self.critic[::2])
        self.init_kwargs = {"policy_dim": policy_dim, "critic_dim": critic_dim,
                            **{k: v for k, v in self.init_kwargs.items() if k != "obs_dim"}}
        self.critic_dim = critic_dim

    @classmethod
    def for_env(cls, env: Any, hidden: tuple[int, ...] | list[int] = (64, 64)) -> GroupedMLPActorCritic:  # type: ignore[override]
        """The network for a ``VecEnv`` observing the two groups (each part's size flattened)."""
        shape = env.observation_shape
        if not is_grouped(shape):
            raise ValueError(f"GroupedMLPActorCritic needs observations with the groups {GROUPS}, got {shape}")
        return cls(int(math.prod(shape[POLICY])), int(math.prod(shape[CRITIC])), int(env.action_dim), hidden,
                   getattr(env, "action_distribution", None))

    def action_params(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:  # type: ignore[override]
        """``obs["policy"] [N, P]`` → the distribution's parameters; the critic group is never read."""
        return super().action_params(obs[POLICY])

    def value(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:  # type: ignore[override]
        """``obs["policy"] [N, P]``, ``obs["critic"] [N, C]`` → V ``[N]``."""
        return super().value(torch.cat([self._flat(obs[POLICY]), self._flat(obs[CRITIC])], dim=1))


__all__ = ["CRITIC", "GROUPS", "POLICY", "GroupedMLPActorCritic", "is_grouped", "without_critic"]
