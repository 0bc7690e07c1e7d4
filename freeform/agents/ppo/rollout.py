"""A rollout's storage, and the layout of a minibatch's samples as named columns.

Shapes: ``T`` = ``rollout_steps``, ``N`` = ``env.num_envs``, ``A`` = the action size, ``P_i`` the sizes of the action
distribution's parameters (``param_dims``), ``B`` = ``T·N``, ``M`` a minibatch's samples.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

Observation = torch.Tensor | dict[str, torch.Tensor]
"""What an env observes, batched: one tensor ``[N, ...]``, or a dict of them (an env that hands a ``Dict`` space's
parts to the policy as they are, ``from_gymnasium(..., dict_obs=True)``)."""


def obs_map(fn: Callable[[torch.Tensor], torch.Tensor], obs: Observation) -> Observation:
    """``fn`` applied to the observation's tensor, or to each of a dict's."""
    return {k: fn(v) for k, v in obs.items()} if isinstance(obs, Mapping) else fn(obs)


def obs_first(obs: Observation) -> torch.Tensor:
    """The observation's tensor, or a dict's first (for its batch size and storage)."""
    return next(iter(obs.values())) if isinstance(obs, Mapping) else obs


def obs_shapes(obs: Observation) -> object:
    """Shapes for messages: a tuple, or a dict of tuples."""
    return {k: tuple(v.shape) for k, v in obs.items()} if isinstance(obs, Mapping) else tuple(obs.shape)


class Samples(NamedTuple):
    """A minibatch's per-sample floats by name: the layout :func:`minibatch_samples` packs and
    :func:`sample_columns` reads, declared once here (the order of the fields is the order of the columns)."""

    actions: torch.Tensor
    """``[M, A]`` the actions taken (raw, unclipped; indices as floats for a discrete distribution)."""
    old_params: torch.Tensor
    """``[M, P]`` π_old's distribution parameters side by side (``P = Σ param_dims``; a Gaussian's mean, then log σ),
    for the KL term: ``distribution.split`` names them."""
    old_logprobs: torch.Tensor
    """``[M]`` log π_old(action)."""
    old_values: torch.Tensor
    """``[M]`` the rollout's V (PPO2's value clip)."""
    returns: torch.Tensor
    """``[M]`` the value targets."""


def minibatch_samples(
    actions: torch.Tensor, old_params: Sequence[torch.Tensor], old_logprobs: torch.Tensor, old_values: torch.Tensor,
    returns: torch.Tensor,
) -> torch.Tensor:
    """The rollout's per-sample floats side by side, ``[B, A + P + 3]``, in :class:`Samples`' order: ``actions [B,
    A]``, each parameter ``[B, P_i]``, then ``[B]`` each. One tensor, so a minibatch is one gather instead of six
    (≈ 10 µs each at 64 samples on the CPU)."""
    columns = (actions, *old_params, old_logprobs, old_values, returns)
    return torch.cat([c if c.dim() == 2 else c[:, None] for c in columns], dim=1)


def sample_columns(samples: torch.Tensor, action_dim: int) -> Samples:
    """:func:`minibatch_samples`' rows ``[M, A + P + 3]`` -> their named columns (views)."""
    params = samples.shape[1] - action_dim - 3
    actions, old_params, old_logprobs, old_values, returns = samples.split([action_dim, params, 1, 1, 1], dim=1)
    return Samples(actions, old_params, old_logprobs.squeeze(1), old_values.squeeze(1), returns.squeeze(1))



class Sequences(NamedTuple):
    """A recurrent minibatch's S sequences of L steps (truncated BPTT): ``obs [L, S, ...]``; ``state`` the policy's
    state at each sequence's first step (``[S, ...]`` each); ``episode_start [L, S]`` bool (the state is reset
    before such a step); ``mask [L, S]`` bool, the steps that count (False: padding past the rollout's end, or a step
    where the env only reset)."""

    obs: Observation
    state: tuple[torch.Tensor, ...]
    episode_start: torch.Tensor
    mask: torch.Tensor


def chunked(x: torch.Tensor, length: int) -> torch.Tensor:
    """Time-major ``x [T, N, ...]`` cut into ``C = ⌈T / L⌉`` chunks of ``L = length`` steps per env, the last padded
    with zeros: ``[L, C·N, ...]``, sequence ``s = c·N + n`` env n's chunk c (a recurrent policy's training view)."""
    steps = x.shape[0]
    chunks = -(-steps // length)
    pad = chunks * length - steps
    if pad:
        x = torch.cat([x, x.new_zeros(pad, *x.shape[1:])])
    return x.reshape(chunks, length, *x.shape[1:]).transpose(0, 1).reshape(length, -1, *x.shape[2:])


@dataclass
class Rollout:
    """One epoch's samples, on the PPO device. Observations keep the env's dtype (uint8 grids stay uint8).

    ``obs [T, N, *obs_shape]`` (a dict of such for dict observations), ``actions [T, N, A]``, ``logprobs [T, N]``, ``rewards [T, N]``, ``dones [T, N]``
    bool, ``values [T, N]``, ``params`` (π_old's distribution parameters, one ``[T, N, P_i]`` each; a Gaussian's
    ``means``/``log_stds``), ``advantages``/``returns
    [T, N]`` (filled after collection), ``last_value [N]`` (V of the observation after the last step).
    ``truncated [T, N]`` bool (the env's ``info["truncated"]``: ended by a time limit) and ``final_values [T, N]``
    (V of such an episode's last observation, its bootstrap); ``valid [T, N]`` bool (False where the env only reset,
    ``info["autoreset"]``: such samples never enter the loss). ``obs`` holds what the policy saw (normalised, with
    ``obs_norm``) and ``rewards`` what it trained on (scaled, with ``reward_norm``). ``episode_returns [T, N]``: each
    env's raw episode return so far (carried across rollouts); at a done step it is the finished episode's return,
    the one figure that TensorBoard, the console, the design records and the renders all read.
    PPO refills these tensors every epoch (``logprobs``, ``values``, ``rewards`` and the advantages may be replaced
    by new ones): clone what must outlive the next ``train_epoch()``.
    """

    obs: Observation
    actions: torch.Tensor
    logprobs: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    values: torch.Tensor
    params: tuple[torch.Tensor, ...]
    advantages: torch.Tensor
    returns: torch.Tensor
    last_value: torch.Tensor
    truncated: torch.Tensor
    final_values: torch.Tensor
    valid: torch.Tensor
    episode_returns: torch.Tensor
    states: tuple[torch.Tensor, ...] = ()
    """A recurrent policy's state as each step's forward received it (before that step's reset), ``[T, N, ...]``
    each; empty for a feed-forward policy."""
    episode_starts: torch.Tensor | None = None
    """``[T, N]`` bool, a recurrent policy's: the step's observation began an episode (its state was reset first)."""

    def __getitem__(self, name: str) -> torch.Tensor:
        """Dict-style access, ``rollout["obs"]``."""
        return getattr(self, name)

    @property
    def means(self) -> torch.Tensor:
        """A Gaussian policy's means ``[T, N, A]`` (``params[0]``)."""
        return self.params[0]

    @means.setter
    def means(self, value: torch.Tensor) -> None:
        self.params = (value, *self.params[1:])

    @property
    def log_stds(self) -> torch.Tensor:
        """A Gaussian policy's log σ ``[T, N, A]`` (``params[1]``)."""
        return self.params[1]

    @log_stds.setter
    def log_stds(self, value: torch.Tensor) -> None:
        self.params = (self.params[0], value, *self.params[2:])

    @classmethod
    def allocate(
        cls, steps: int, num_envs: int, first_obs: Observation, obs_dtype: torch.dtype | None, action_dim: int,
        param_dims: Sequence[int], device: torch.device, state: Sequence[torch.Tensor] = (),
    ) -> Rollout:
        """Storage for ``steps`` steps of ``num_envs`` envs observing like ``first_obs [N, ...]`` (in ``obs_dtype``,
        None: as observed), acting with ``action_dim`` numbers from a distribution of ``param_dims``; a recurrent
        policy's ``state`` (``[N, ...]`` each) gets a slot per step."""
        f32 = dict(dtype=torch.float32, device=device)
        return cls(
            obs=obs_map(lambda x: torch.zeros((steps, num_envs, *x.shape[1:]), dtype=obs_dtype or x.dtype,
                                              device=device), first_obs),
            actions=torch.zeros((steps, num_envs, action_dim), **f32),
            logprobs=torch.zeros((steps, num_envs), **f32),
            rewards=torch.zeros((steps, num_envs), **f32),
            dones=torch.zeros((steps, num_envs), dtype=torch.bool, device=device),
            values=torch.zeros((steps, num_envs), **f32),
            params=tuple(torch.zeros((steps, num_envs, p), **f32) for p in param_dims),
            advantages=torch.zeros((steps, num_envs), **f32),
            returns=torch.zeros((steps, num_envs), **f32),
            last_value=torch.zeros((num_envs,), **f32),
            truncated=torch.zeros((steps, num_envs), dtype=torch.bool, device=device),
            final_values=torch.zeros((steps, num_envs), **f32),
            valid=torch.ones((steps, num_envs), dtype=torch.bool, device=device),
            episode_returns=torch.zeros((steps, num_envs), **f32),
            states=tuple(torch.zeros((steps, *s.shape), dtype=s.dtype, device=device) for s in state),
            episode_starts=torch.zeros((steps, num_envs), dtype=torch.bool, device=device) if state else None,
        )


__all__ = ["Sequences", "Observation", "Rollout", "Samples", "chunked", "minibatch_samples", "obs_first", "obs_map",
           "obs_shapes", "sample_columns"]
