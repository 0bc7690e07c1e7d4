"""Gymnasium both ways: any ``gymnasium.vector.VectorEnv`` as a freeform :class:`~freeform.envs.VecEnv`
(:func:`from_gymnasium`, so ``freeform.agents.PPO`` trains MuJoCo or your own env), and any freeform ``VecEnv`` as a
``gymnasium.vector.VectorEnv`` (:func:`to_gymnasium`, so SB3/CleanRL code trains on the design env's tasks).

Gymnasium is optional (``pip install 'freeform[gym]'``); it is imported when this module is.

Episode ends (Gymnasium 1.x): ``terminated`` and ``truncated`` are kept apart. A freeform env reports ``done =
terminated | truncated`` and, in ``info``, ``truncated`` (a time limit cut the episode: PPO bootstraps it with
V(``final_obs``)) and ``final_obs`` (the episode's last observation). How the vector env resets its envs
(``metadata["autoreset_mode"]``):

- ``SAME_STEP``: the step that ends an episode returns the next episode's first observation; the last one is in
  Gymnasium's ``info["final_obs"]``. Nothing is lost: the recommended mode
  (``gym.make_vec(..., vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})``).
- ``NEXT_STEP`` (Gymnasium's default): the step after an episode's end only resets that env (its action is ignored,
  reward 0). The adapter flags it in ``info["autoreset"]``; PPO keeps such samples out of the loss and the episode
  lengths, so no reset step is ever trained on as if it followed the last one.
- ``DISABLED``: the adapter resets the finished envs itself (``reset(options={"reset_mask": done})``).
"""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

__all__ = ["ActionDecoder", "DictEncoder", "FreeformVectorEnv", "GymnasiumVecEnv", "ObservationEncoder", "from_gymnasium",
           "to_gymnasium"]


_LEAVES = (gym.spaces.Box, gym.spaces.Discrete, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary)


class ObservationEncoder:
    """A Gymnasium observation space's batched observations as one tensor's rows, as the policy reads them.

    A ``Box`` stays as it is (``uint8`` images stay ``uint8`` until the network; any other dtype becomes float32);
    every other space is flattened into float32 ``[N, D]``: ``Discrete`` and each entry of ``MultiDiscrete`` one-hot,
    ``MultiBinary`` as 0/1, ``Dict`` and ``Tuple`` their parts side by side in the space's order — row for row what
    ``gymnasium.spaces.flatten`` gives, batched. Spaces of no fixed size (``Text``, ``Graph``, ``Sequence``,
    ``OneOf``) are refused, by name.
    """

    def __init__(self, space: gym.spaces.Space) -> None:
        self.space = space
        self._check(space, "observation")
        self.box = isinstance(space, gym.spaces.Box)
        if self.box:
            self.dtype = np.uint8 if space.dtype == np.uint8 else np.float32
            self.shape: tuple[int, ...] = tuple(space.shape)
        else:
            self.dtype = np.float32
            self.shape = (int(gym.spaces.flatdim(space)),)

    @staticmethod
    def _check(space: gym.spaces.Space, path: str) -> None:
        if isinstance(space, gym.spaces.Dict):
            for key, part in space.spaces.items():
                ObservationEncoder._check(part, f"{path}[{key!r}]")
        elif isinstance(space, gym.spaces.Tuple):
            for i, part in enumerate(space.spaces):
                ObservationEncoder._check(part, f"{path}[{i}]")
        elif not isinstance(space, _LEAVES):
            raise ValueError(f"from_gymnasium cannot encode the {type(space).__name__} space at {path} ({space}): "
                             "observations must be Box, Discrete, MultiDiscrete, MultiBinary, or Dict/Tuple of them")

    def batch(self, x: Any, n: int) -> np.ndarray:
        """A vector env's observations of ``n`` envs → ``[n, *shape]`` in ``dtype``, always a new array (a vector env
        built with ``copy=False`` reuses its buffers, and PPO keeps each step's observations for the rollout)."""
        if self.box:
            return np.array(x, dtype=self.dtype).reshape(n, *self.shape)
        return np.concatenate(list(self._parts(self.space, x, n)), axis=1)

    def row(self, x: Any) -> np.ndarray:
        """One env's observation (Gymnasium's ``final_obs`` entries) → ``[*shape]``."""
        if self.box:
            return np.asarray(x, dtype=self.dtype).reshape(self.shape)
        return np.asarray(gym.spaces.flatten(self.space, x), dtype=np.float32)

    @classmethod
    def _parts(cls, space: gym.spaces.Space, x: Any, n: int) -> Any:
        if isinstance(space, gym.spaces.Dict):
            for key, part in space.spaces.items():
                yield from cls._parts(part, x[key], n)
        elif isinstance(space, gym.spaces.Tuple):
            for i, part in enumerate(space.spaces):
                yield from cls._parts(part, x[i], n)
        elif isinstance(space, gym.spaces.Discrete):
            yield _one_hot(np.asarray(x).reshape(n, 1) - int(space.start), [int(space.n)])
        elif isinstance(space, gym.spaces.MultiDiscrete):
            entries = (np.asarray(x) - space.start).reshape(n, -1)
            yield _one_hot(entries, [int(k) for k in space.nvec.reshape(-1)])
        else:  # Box, MultiBinary
            yield np.asarray(x, dtype=np.float32).reshape(n, -1)


class DictEncoder:
    """A ``Dict`` observation space's parts kept apart (``from_gymnasium(..., dict_obs=True)``): a dict of arrays,
    each part encoded by its own :class:`ObservationEncoder`, for a network that reads them by name."""

    def __init__(self, space: gym.spaces.Space) -> None:
        if not isinstance(space, gym.spaces.Dict):
            raise ValueError(f"dict_obs needs a Dict observation space, got {type(space).__name__} ({space})")
        self.parts = {key: ObservationEncoder(part) for key, part in space.spaces.items()}
        self.shape = {key: part.shape for key, part in self.parts.items()}

    def batch(self, x: Any, n: int) -> dict[str, np.ndarray]:
        return {key: part.batch(x[key], n) for key, part in self.parts.items()}

    def row(self, x: Any) -> dict[str, np.ndarray]:
        return {key: part.row(x[key]) for key, part in self.parts.items()}


def _one_hot(indices: np.ndarray, sizes: list[int]) -> np.ndarray:
    """``indices [n, K]`` (entry k in 0 … sizes[k] − 1) → float32 ``[n, Σ sizes]``, each entry one-hot in its block."""
    out = np.zeros((indices.shape[0], sum(sizes)), dtype=np.float32)
    offsets = np.cumsum([0, *sizes[:-1]])
    out[np.arange(indices.shape[0])[:, None], offsets[None, :] + indices] = 1.0
    return out


class ActionDecoder:
    """PPO's actions ``[N, A]`` → what a Gymnasium vector env takes, in its action space's shape and dtype: a
    ``Box`` clipped to its bounds (PPO stores what it sampled, unclipped); ``Discrete``/``MultiDiscrete`` indices
    shifted by the space's ``start``; ``MultiBinary`` bits. ``distribution``: the one PPO trains for the space."""

    def __init__(self, space: gym.spaces.Space) -> None:
        from freeform.distributions import (
            for_space,  # (agents do not import envs; this direction is free)
        )

        self.distribution = for_space(space)  # refuses any other space, by name
        self.space = space
        self.shape = tuple(space.shape) if space.shape is not None else ()
        self.dim = self.distribution.action_dim
        self.dtype = space.dtype
        self.box = isinstance(space, gym.spaces.Box)
        if self.box:
            self.low = np.broadcast_to(space.low, self.shape).reshape(-1).astype(self.dtype)
            self.high = np.broadcast_to(space.high, self.shape).reshape(-1).astype(self.dtype)
        start = getattr(space, "start", 0)
        self.start = np.asarray(start, dtype=np.int64).reshape(-1)

    def __call__(self, actions: torch.Tensor, n: int) -> np.ndarray:
        if self.box:
            if actions.dtype in (torch.float32, torch.float64) and actions.device.type == "cpu" and not actions.requires_grad:
                raw = actions.numpy()  # PPO's case: .detach().to() would be two more operations, each a dispatch
            else:
                wide = actions.dtype if actions.dtype in (torch.float32, torch.float64) else torch.float32  # no bf16 in numpy
                raw = actions.detach().to("cpu", wide).numpy()
            raw = raw.reshape(n, self.dim)
            # np.minimum/np.maximum: np.clip's checks cost more than the clip at these sizes.
            clipped = np.minimum(np.maximum(raw, self.low), self.high).astype(self.dtype, copy=False)
            return clipped.reshape(n, *self.shape)
        raw = actions.detach().to("cpu").numpy().reshape(n, self.dim)
        indices = np.rint(raw).astype(np.int64) + self.start
        return indices.astype(self.dtype).reshape(n, *self.shape)


def _mode(vector_env: gym.vector.VectorEnv) -> AutoresetMode:
    mode = vector_env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
    return AutoresetMode(mode) if not isinstance(mode, AutoresetMode) else mode


class GymnasiumVecEnv:
    """A ``gymnasium.vector.VectorEnv`` as a freeform ``VecEnv`` (build it with :func:`from_gymnasium`).

    Actions: ``Box`` (a Gaussian policy; clipped to the bounds for the env, PPO stores what it sampled, unclipped),
    ``Discrete``, ``MultiDiscrete``, ``MultiBinary`` (``action_distribution`` says which distribution PPO trains;
    :class:`ActionDecoder`). Observations: a ``Box`` as it is (float32, or ``uint8`` images kept ``uint8``), any
    other space flattened to float32 with one-hot discrete parts (:class:`ObservationEncoder`); with ``dict_obs`` a
    ``Dict`` space's parts kept apart, a dict of tensors (:class:`DictEncoder`).

    ``step(actions [N, A])`` returns tensors on ``device``: ``obs [N, *obs_shape]``, ``reward [N]``, ``done [N]``
    (terminated or truncated) and ``info`` with ``truncated [N]`` (truncated and not terminated), ``terminated [N]``,
    ``final_obs [N, *obs_shape]`` when an episode ended (rows of the other envs are their current observation), and in
    ``NEXT_STEP`` mode ``autoreset [N]`` (this step only reset the env). The vector env's own info is kept under
    ``gym_info``.
    """

    def __init__(self, vector_env: gym.vector.VectorEnv, seed: int | None = None, device: str | torch.device = "cpu",
                 dict_obs: bool = False):
        space = vector_env.single_observation_space
        self.encoder = DictEncoder(space) if dict_obs else ObservationEncoder(space)
        self.decoder = ActionDecoder(vector_env.single_action_space)
        self.vector_env = vector_env
        self.num_envs = int(vector_env.num_envs)
        self.observation_shape = self.encoder.shape
        self.action_distribution = self.decoder.distribution
        """What PPO trains for the action space (``freeform.distributions``)."""
        self.action_dim = self.decoder.dim
        self.device = torch.device(device)
        self.seed = seed
        self.autoreset_mode = _mode(vector_env)
        self._resetting = np.zeros(self.num_envs, dtype=bool)  # NEXT_STEP: these envs' next step only resets them

    def _tensor(self, x: Any) -> Any:
        # Cast and reshape in numpy (with one env a torch op costs several times a numpy one).
        if isinstance(x, dict):
            return {key: self._tensor(part) for key, part in x.items()}
        x = torch.from_numpy(x)
        return x if self.device.type == "cpu" else x.to(self.device)

    def _flags(self, x: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(x)
        return x if self.device.type == "cpu" else x.to(self.device)

    def reset(self, seed: int | None = None) -> Any:
        """Reset every env (seeded with ``seed``, else the adapter's ``seed``; Gymnasium gives env i seed + i): the
        first observations, a tensor (a dict of them with ``dict_obs``)."""
        seed = seed if seed is not None else self.seed
        obs, _ = self.vector_env.reset(seed=seed)
        self._resetting[:] = False
        return self._tensor(self.encoder.batch(obs, self.num_envs))

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        obs, reward, terminated, truncated, gym_info = self.vector_env.step(self.decoder(actions, self.num_envs))
        terminated, truncated = np.asarray(terminated, dtype=bool), np.asarray(truncated, dtype=bool)
        done = terminated | truncated
        n, encode = self.num_envs, self.encoder
        encoded = encode.batch(obs, n)
        info: dict[str, Any] = {"gym_info": gym_info}
        final_obs = None
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            info["autoreset"] = self._flags(self._resetting.copy())
            self._resetting = done.copy()
            if done.any():
                final_obs = encoded  # the episode's last observation; the reset comes with the next step
        elif self.autoreset_mode == AutoresetMode.SAME_STEP:
            if done.any():
                final_obs = _copy(encoded)
                mask = np.asarray(gym_info.get("_final_obs", done), dtype=bool)
                for i in np.flatnonzero(mask):
                    _set_row(final_obs, i, encode.row(gym_info["final_obs"][i]))
        else:  # DISABLED: reset the finished envs here
            if done.any():
                final_obs = encoded
                obs, _ = self.vector_env.reset(options={"reset_mask": done})
                encoded = encode.batch(obs, n)
        info["terminated"] = self._flags(terminated)
        info["truncated"] = self._flags(truncated & ~terminated)
        if final_obs is not None:
            info["final_obs"] = self._tensor(final_obs)
        reward = np.array(reward, dtype=np.float32).reshape(n)
        return self._tensor(encoded), self._tensor(reward), self._flags(done), info

    def state_dict(self) -> dict[str, Any]:
        """The adapter's own state (which envs reset next step) and the vector env's ``state_dict()`` if it has one.
        (Gymnasium's MuJoCo envs have none: a resumed run then continues with freshly reset envs.)"""
        state: dict[str, Any] = {"per_env": {"resetting": torch.as_tensor(self._resetting.copy())}}
        if hasattr(self.vector_env, "state_dict"):
            state["vector_env"] = self.vector_env.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the adapter's state; the vector env's own only where it saves one. Gymnasium's envs (MuJoCo's
        among them) do not: they go on from a fresh reset, so a resumed run equals an uninterrupted one in every
        weight and statistic PPO saved, but not in its episodes (the ones in progress at the checkpoint are lost)."""
        self._resetting = state["per_env"]["resetting"].cpu().numpy().astype(bool).copy()
        if "vector_env" in state and hasattr(self.vector_env, "load_state_dict"):
            self.vector_env.load_state_dict(state["vector_env"])
        else:
            warnings.warn(
                f"resuming on {type(self.vector_env).__name__}, which cannot save its state (Gymnasium's envs, "
                "MuJoCo's among them): its environments start from a fresh reset, the episodes in progress at the "
                "checkpoint are lost, and the run will not equal an uninterrupted one", RuntimeWarning, stacklevel=2)

    def close(self) -> None:
        self.vector_env.close()


def _copy(x: Any) -> Any:
    return {key: part.copy() for key, part in x.items()} if isinstance(x, dict) else x.copy()


def _set_row(x: Any, i: int, row: Any) -> None:
    if isinstance(x, dict):
        for key, part in x.items():
            part[i] = row[key]
    else:
        x[i] = row


def from_gymnasium(
    vector_env: gym.vector.VectorEnv, seed: int | None = None, device: str | torch.device = "cpu",
    dict_obs: bool = False,
) -> GymnasiumVecEnv:
    """Wrap a ``gymnasium.vector.VectorEnv`` (sync or async; the spaces :class:`GymnasiumVecEnv` lists) as a
    freeform ``VecEnv`` for ``freeform.agents.PPO`` (see :class:`GymnasiumVecEnv` and the module docstring for the
    episode ends). A space it cannot train on is refused here, by name.

    ``dict_obs=True`` (a ``Dict`` observation space): observations are a dict of tensors, one per part (each
    encoded as above), ``observation_shape`` a dict of shapes, for a policy of your own that reads them by name;
    by default every space is flattened into one tensor, which ``MLPActorCritic`` reads.

    ``seed`` seeds the first ``reset`` when the caller passes none (PPO passes ``config.seed``).
    """
    if not isinstance(vector_env, gym.vector.VectorEnv):
        raise ValueError(f"from_gymnasium needs a gymnasium.vector.VectorEnv, got {type(vector_env).__name__}")
    return GymnasiumVecEnv(vector_env, seed=seed, device=device, dict_obs=dict_obs)


# ---------------------------------------------------------------------------------------------------------------
# The other direction.
# ---------------------------------------------------------------------------------------------------------------


class FreeformVectorEnv(gym.vector.VectorEnv):
    """A freeform ``VecEnv`` as a ``gymnasium.vector.VectorEnv`` (build it with :func:`to_gymnasium`).

    numpy in and out; ``SAME_STEP`` autoreset (a freeform env resets its finished envs itself): the step that ends an
    episode returns the next episode's first observation and puts the last one in ``info["final_obs"]`` (with the
    ``_final_obs`` mask). ``terminated = done & ~info["truncated"]`` (the design env never truncates).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        env: Any,
        observation_space: gym.spaces.Box | None = None,
        action_space: gym.spaces.Space | None = None,
    ) -> None:
        self.env = env
        self.num_envs = int(env.num_envs)
        self.single_observation_space = observation_space or _default_observation_space(env)
        self.single_action_space = action_space or _default_action_space(env)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self._obs_dtype = self.single_observation_space.dtype

    def _obs(self, obs: torch.Tensor) -> np.ndarray:
        return obs.detach().cpu().numpy().astype(self._obs_dtype, copy=True)

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):  # type: ignore[override]
        super().reset(seed=seed if isinstance(seed, int) or seed is None else seed[0])
        if options and "reset_mask" in options:
            raise ValueError("a freeform env resets its environments together: reset_mask is not supported")
        return self._obs(self.env.reset(seed=seed if isinstance(seed, int) or seed is None else seed[0])), {}

    def step(self, actions: Any):  # type: ignore[override]
        discrete = not isinstance(self.single_action_space, gym.spaces.Box)
        action = torch.as_tensor(np.asarray(actions, dtype=np.int64 if discrete else np.float32)).reshape(self.num_envs, -1)
        obs, reward, done, info = self.env.step(action.to(self.env.device))
        done = done.detach().cpu().numpy().astype(bool)
        truncated = info.get("truncated")
        truncated = np.zeros_like(done) if truncated is None else truncated.detach().cpu().numpy().astype(bool) & done
        out: dict[str, Any] = {}
        if done.any():
            final = info.get("final_obs", info.get("final_grids"))  # the design env names its last grids so
            if final is not None:
                final = self._obs(final)
                out["final_obs"] = np.array([final[i] if done[i] else None for i in range(self.num_envs)], dtype=object)
                out["_final_obs"] = done.copy()
        return (
            self._obs(obs),
            reward.detach().cpu().numpy().astype(np.float64),
            done & ~truncated,
            truncated,
            out,
        )

    def close_extras(self, **kwargs: Any) -> None:
        if hasattr(self.env, "close"):
            self.env.close()


def _default_observation_space(env: Any) -> gym.spaces.Box:
    if isinstance(env.observation_shape, dict):
        raise ValueError("to_gymnasium needs an observation_space for an env that observes a dict of tensors "
                         f"{env.observation_shape}: pass a gymnasium.spaces.Dict")
    shape = tuple(env.observation_shape)
    materials = getattr(env, "materials", None)
    if materials is not None:  # the design env: uint8 grids of material indices 0 … k − 1
        return gym.spaces.Box(0, int(materials) - 1, shape, dtype=np.uint8)
    return gym.spaces.Box(-np.inf, np.inf, shape, dtype=np.float32)


def _default_action_space(env: Any) -> gym.spaces.Space:
    from freeform.distributions import Bernoulli, Categorical, MultiCategorical

    dist = getattr(env, "action_distribution", None)  # an env with discrete actions says so
    if isinstance(dist, Categorical):
        return gym.spaces.Discrete(dist.n)
    if isinstance(dist, MultiCategorical):
        return gym.spaces.MultiDiscrete(list(dist.nvec))
    if isinstance(dist, Bernoulli):
        return gym.spaces.MultiBinary(dist.n)
    bound = float(getattr(env, "action_bound", np.inf))  # the design env clips actions to ±action_bound
    return gym.spaces.Box(-bound, bound, (int(env.action_dim),), dtype=np.float32)


def to_gymnasium(
    env: Any, observation_space: gym.spaces.Box | None = None, action_space: gym.spaces.Box | None = None
) -> FreeformVectorEnv:
    """Expose a freeform ``VecEnv`` (e.g. ``DesignEnv`` with any task) as a ``gymnasium.vector.VectorEnv``.

    Spaces default to: observations ``Box(0, k − 1, uint8)`` for an env with ``materials`` (the design env), else
    ``Box(−∞, ∞, float32)``; actions ``Discrete``/``MultiDiscrete``/``MultiBinary`` for an env whose
    ``action_distribution`` is discrete, else ``Box(−action_bound, action_bound, float32)`` (the design env's clip),
    or unbounded.
    """
    return FreeformVectorEnv(env, observation_space, action_space)
