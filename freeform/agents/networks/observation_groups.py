"""Observation groups: a dict observation with the keys ``"policy"`` and ``"critic"`` (rsl_rl's observation groups,
skrl's states). The actor reads only ``"policy"``; the critic reads both — ``"critic"`` holds what only the critic may
see (privileged state: what the sensors lack). PPO normalises each group by its own statistics (``obs_norm``), and an
exported actor (``PPO.export``) takes ``"policy"`` alone.

A Gymnasium env whose observation space is ``Dict({"policy": ..., "critic": ...})`` arrives so through
``freeform.envs.from_gymnasium(..., dict_obs=True)``; :class:`freeform.agents.MLPActorCritic` ``.for_env`` then builds
the grouped network (``freeform.agents.networks.GroupedMLPActorCritic``). This module names the groups and imports
nothing of freeform: the networks, the controllers and PPO read it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

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


__all__ = ["CRITIC", "GROUPS", "POLICY", "is_grouped", "without_critic"]
