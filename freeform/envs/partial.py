"""Partial observability for Gymnasium tasks: ``HideEntries`` hides entries of a ``Box`` observation from the policy
— CartPole without its velocities, Pendulum without its angular velocity: tasks that need memory — and, with
``critic=True``, hands them to the critic alone as the ``"critic"`` observation group (a privileged critic:
``freeform.agents.networks.observation_groups``; read it through ``from_gymnasium(..., dict_obs=True)``).

``NoisyEntries`` adds Gaussian noise to what the policy observes and, with ``critic=True``, hands the clean
observation to the critic alone: rsl_rl's legged-robot setting (noisy sensors for the actor, the simulator's true
state for the critic), the asymmetric actor-critic test of ``docs/ppo.md``.

Gymnasium is optional (``pip install 'freeform[gym]'``); it is imported when this module is.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np


class HideEntries(gym.ObservationWrapper):
    """A ``Box`` observation less the entries ``hidden`` (indices into the flattened observation). ``critic=False``:
    the observation is the kept entries, ``Box [K]``; ``critic=True``: ``Dict(policy=kept [K], critic=hidden
    [H])``."""

    def __init__(self, env: gym.Env, hidden: Sequence[int], critic: bool = False) -> None:
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"HideEntries needs a Box observation space, got {space}")
        size = int(np.prod(space.shape))
        hidden = sorted({int(i) for i in hidden})
        if not hidden or hidden[0] < 0 or hidden[-1] >= size or len(hidden) == size:
            raise ValueError(f"hidden must name some, not all, of the observation's {size} entries, got {hidden}")
        self.hidden = np.array(hidden)
        self.kept = np.array([i for i in range(size) if i not in hidden])
        low, high = space.low.reshape(-1), space.high.reshape(-1)

        def box(idx: np.ndarray) -> gym.spaces.Box:
            return gym.spaces.Box(low[idx], high[idx], (len(idx),), space.dtype)

        self.critic = critic
        self.observation_space = (gym.spaces.Dict({"policy": box(self.kept), "critic": box(self.hidden)}) if critic
                                  else box(self.kept))

    def observation(self, observation: Any) -> Any:
        flat = np.asarray(observation).reshape(-1)
        if self.critic:
            return {"policy": flat[self.kept], "critic": flat[self.hidden]}
        return flat[self.kept]


class NoisyEntries(gym.ObservationWrapper):
    """A ``Box`` observation with independent Gaussian noise of standard deviation ``std`` (one per entry of the
    flattened observation, or one for all; ≥ 0, 0: that entry exact) added to every observation the policy sees,
    drawn from the wrapper's ``np_random`` (seeded by ``reset(seed=...)``). ``critic=False``: ``Box`` of the same
    shape, unbounded; ``critic=True``: ``Dict(policy=noisy, critic=clean)``, each flattened."""

    def __init__(self, env: gym.Env, std: float | Sequence[float], critic: bool = False) -> None:
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"NoisyEntries needs a Box observation space, got {space}")
        size = int(np.prod(space.shape))
        std = np.asarray(std, dtype=np.float64)
        std = np.full(size, float(std)) if std.ndim == 0 else std
        if std.shape != (size,) or not np.all(np.isfinite(std)) or np.any(std < 0):
            raise ValueError(f"std must be one finite number >= 0 or {size} of them (one per observation entry), "
                             f"got {std.tolist()}")
        self.std, self.critic = std.astype(space.dtype), critic
        noisy = gym.spaces.Box(-np.inf, np.inf, (size,), space.dtype)
        clean = gym.spaces.Box(space.low.reshape(-1), space.high.reshape(-1), (size,), space.dtype)
        self.observation_space = gym.spaces.Dict({"policy": noisy, "critic": clean}) if critic else noisy

    def observation(self, observation: Any) -> Any:
        flat = np.asarray(observation).reshape(-1)
        noisy = (flat + self.std * self.np_random.standard_normal(flat.shape)).astype(flat.dtype)
        return {"policy": noisy, "critic": flat} if self.critic else noisy


__all__ = ["HideEntries", "NoisyEntries"]
