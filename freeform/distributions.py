"""The action distributions PPO can train, decided once from the action space and outside the algorithm.

A distribution here is a small frozen description (its sizes) with pure functions of tensors: ``sample`` from
pre-drawn noise, ``mode`` (the deterministic action), ``log_prob``, ``entropy`` and ``kl``. The policy's outputs are the
distribution's parameters (``param_dims``, in order) followed by the value.

=====================  ========================  ==================================  ==========================
distribution           Gymnasium action space    policy outputs (``params``)         actions (stored ``[N, A]``)
=====================  ========================  ==================================  ==========================
:class:`DiagGaussian`  ``Box``                   ``mean [N, A]``, ``log_std [N, A]``  raw floats (the env clips)
:class:`Categorical`   ``Discrete(n)``           ``logits [N, n]``                   ``[N, 1]`` index 0 … n − 1
:class:`MultiCategorical` ``MultiDiscrete``      ``logits [N, Σ nvec]``              ``[N, K]`` one index each
:class:`Bernoulli`     ``MultiBinary(n)``        ``logits [N, n]``                   ``[N, n]`` 0 or 1
:class:`MaskedDiagGaussian` (an env's own)      ``mean, log_std, mask [N, A]``      raw floats; only the masked
                                                                                     entries count
=====================  ========================  ==================================  ==========================

The loss, the KL penalty and the sampling read only these functions; the one thing PPO asks of the kind is the
logged σ (``action_std``), a Gaussian's own figure. Actions are stored as floats (indices are exact below 2²⁴) so
that every distribution shares the rollout's layout;
:meth:`ActionDistribution.env_actions` gives the env integers. Sampling reads noise PPO draws for the whole rollout at
once (``noise_kind``: standard normal for the Gaussian, uniform [0, 1) for the others; one number per action entry):
a Gaussian action is ``mean + σ·z``, a categorical one the inverse CDF at ``u``, a Bernoulli one ``u < p``.

Shapes: ``[...]`` any leading batch dimensions (``[N]`` when acting, ``[M]`` in a minibatch, ``[T, N]`` over a
rollout); ``A`` = ``action_dim``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)

Params = tuple[torch.Tensor, ...]
"""A distribution's parameters, one tensor per entry of ``param_dims`` (each ``[..., param_dims[i]]``)."""


# ------------------------------------------------------------------------------------------------ the pure functions


def gaussian_log_prob_entries(actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log N(actions; mean, exp(log_std)) of each entry: ``[..., A]`` → ``[..., A]``."""
    z = (actions - mean) * torch.exp(-log_std)
    return -0.5 * z.square() - log_std - LOG_SQRT_2PI


def gaussian_entropy_entries(log_std: torch.Tensor) -> torch.Tensor:
    """Each entry's entropy of a diagonal Gaussian: ``[..., A]`` → ``[..., A]``."""
    return log_std + 0.5 + LOG_SQRT_2PI


def gaussian_kl_entries(mean0: torch.Tensor, log_std0: torch.Tensor, mean1: torch.Tensor,
                        log_std1: torch.Tensor) -> torch.Tensor:
    """Each entry's KL(N(mean0, σ0) ‖ N(mean1, σ1)): ``[..., A]`` → ``[..., A]``."""
    var_ratio = torch.exp(2.0 * (log_std0 - log_std1))
    mahalanobis = ((mean0 - mean1) * torch.exp(-log_std1)).square()
    return log_std1 - log_std0 + 0.5 * (var_ratio + mahalanobis) - 0.5


def gaussian_log_prob(actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log N(actions; mean, exp(log_std)) summed over the last dim: ``[..., A]`` → ``[...]``."""
    return gaussian_log_prob_entries(actions, mean, log_std).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian, summed over the last dim: ``[..., A]`` → ``[...]``."""
    return gaussian_entropy_entries(log_std).sum(-1)


def gaussian_kl(mean0: torch.Tensor, log_std0: torch.Tensor, mean1: torch.Tensor, log_std1: torch.Tensor) -> torch.Tensor:
    """KL(N(mean0, σ0) ‖ N(mean1, σ1)) of diagonal Gaussians, summed over the last dim: ``[..., A]`` → ``[...]``."""
    return gaussian_kl_entries(mean0, log_std0, mean1, log_std1).sum(-1)


def categorical_log_prob(logits: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """log softmax(logits)[index]: logits ``[..., n]``, index ``[...]`` (any numeric dtype) → ``[...]``."""
    return logits.log_softmax(-1).gather(-1, index.long().unsqueeze(-1)).squeeze(-1)


def categorical_entropy(logits: torch.Tensor) -> torch.Tensor:
    """−Σ p log p of softmax(logits): ``[..., n]`` → ``[...]`` (0·log 0 counted as 0)."""
    log_p = logits.log_softmax(-1)
    return -(log_p.exp() * log_p).sum(-1)


def categorical_kl(logits0: torch.Tensor, logits1: torch.Tensor) -> torch.Tensor:
    """KL(softmax(logits0) ‖ softmax(logits1)) = Σ p0 (log p0 − log p1): ``[..., n]`` → ``[...]``."""
    log_p0, log_p1 = logits0.log_softmax(-1), logits1.log_softmax(-1)
    return (log_p0.exp() * (log_p0 - log_p1)).sum(-1)


def categorical_sample(logits: torch.Tensor, uniform: torch.Tensor) -> torch.Tensor:
    """The inverse CDF of softmax(logits) at ``uniform [...]`` ∈ [0, 1): the index ``[...]`` (float)."""
    cdf = logits.softmax(-1).cumsum(-1)
    index = (cdf <= uniform.unsqueeze(-1)).sum(-1)  # how many categories' cumulative mass lies at or below u
    return index.clamp_max(logits.shape[-1] - 1).to(logits.dtype)  # (rounding may leave cdf[-1] a hair below 1)


def bernoulli_log_prob(logits: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
    """Σ log Bernoulli(bits; sigmoid(logits)) over the last dim: ``[..., n]`` → ``[...]``; bits 0 or 1."""
    return -F.binary_cross_entropy_with_logits(logits, bits.to(logits.dtype), reduction="none").sum(-1)


def bernoulli_entropy(logits: torch.Tensor) -> torch.Tensor:
    """Σ of each bit's entropy, −p log p − (1 − p) log(1 − p): ``[..., n]`` → ``[...]``."""
    p = torch.sigmoid(logits)
    return F.binary_cross_entropy_with_logits(logits, p, reduction="none").sum(-1)


def bernoulli_kl(logits0: torch.Tensor, logits1: torch.Tensor) -> torch.Tensor:
    """Σ KL(Bernoulli(p0) ‖ Bernoulli(p1)) over the last dim, from logits: ``[..., n]`` → ``[...]``."""
    p0 = torch.sigmoid(logits0)
    # KL = H(p0, p1) − H(p0): two cross-entropies, each stable in the logits
    cross = F.binary_cross_entropy_with_logits(logits1, p0, reduction="none")
    own = F.binary_cross_entropy_with_logits(logits0, p0, reduction="none")
    return (cross - own).sum(-1)


def _check_size(value: Any, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"an action distribution's {name} must be a positive int, got {value!r}")


def _total(parts: list[torch.Tensor]) -> torch.Tensor:
    """The sum of independent parts' log-probabilities (entropies, KLs); one part costs no operation."""
    total = parts[0]
    for part in parts[1:]:
        total = total + part
    return total


# ------------------------------------------------------------------------------------------------ the distributions


@dataclass(frozen=True)
class ActionDistribution:
    """What every distribution declares: ``action_dim`` A (numbers per action), ``param_dims`` (the sizes of the
    policy's parameter outputs, in order), ``noise_kind`` ("normal" or "uniform", A numbers per action) and whether
    its actions are integers (``discrete``). Subclasses implement the five functions."""

    @property
    def action_dim(self) -> int:
        raise NotImplementedError

    @property
    def param_dims(self) -> tuple[int, ...]:
        raise NotImplementedError

    noise_kind = "uniform"
    discrete = True

    def sample(self, params: Params, noise: torch.Tensor) -> torch.Tensor:
        """Actions ``[..., A]`` (float) from the parameters and ``noise [..., A]`` of ``noise_kind``."""
        raise NotImplementedError

    def mode(self, params: Params) -> torch.Tensor:
        """The most likely action ``[..., A]`` (the Gaussian's mean): the deterministic policy."""
        raise NotImplementedError

    def log_prob(self, params: Params, actions: torch.Tensor) -> torch.Tensor:
        """log π(actions) ``[...]`` for actions ``[..., A]``."""
        raise NotImplementedError

    def entropy(self, params: Params) -> torch.Tensor:
        """H(π) ``[...]``."""
        raise NotImplementedError

    def kl(self, old: Params, new: Params) -> torch.Tensor:
        """KL(π_old ‖ π_new) ``[...]``: PPO's penalty and its statistic ``approx_kl``."""
        raise NotImplementedError

    def env_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """What the env is given for stored actions ``[N, A]``: int64 indices for a discrete distribution, the same
        tensor for a continuous one."""
        return actions.long() if self.discrete else actions

    def split(self, flat: torch.Tensor) -> Params:
        """One tensor ``[..., Σ param_dims]`` (a minibatch's stored columns) → the parameters (views)."""
        return tuple(flat.split(list(self.param_dims), dim=-1))

    def spec(self) -> dict[str, Any]:
        """A plain description that :func:`from_spec` rebuilds (a network's ``init_kwargs`` may hold it)."""
        raise NotImplementedError


@dataclass(frozen=True)
class DiagGaussian(ActionDistribution):
    """π = N(mean, diag(exp(log_std))²) over ``dim`` raw (unclipped) floats."""

    dim: int
    noise_kind = "normal"
    discrete = False

    def __post_init__(self) -> None:
        _check_size(self.dim, "dim")

    @property
    def action_dim(self) -> int:
        return self.dim

    @property
    def param_dims(self) -> tuple[int, ...]:
        return (self.dim, self.dim)

    def sample(self, params: Params, noise: torch.Tensor) -> torch.Tensor:
        mean, log_std = params
        return torch.addcmul(mean, torch.exp(log_std), noise)

    def mode(self, params: Params) -> torch.Tensor:
        return params[0]

    def log_prob(self, params: Params, actions: torch.Tensor) -> torch.Tensor:
        return gaussian_log_prob(actions, *params)

    def entropy(self, params: Params) -> torch.Tensor:
        return gaussian_entropy(params[1])

    def kl(self, old: Params, new: Params) -> torch.Tensor:
        return gaussian_kl(*old, *new)

    def spec(self) -> dict[str, Any]:
        return {"kind": "gaussian", "dim": self.dim}


@dataclass(frozen=True)
class MaskedDiagGaussian(DiagGaussian):
    """A diagonal Gaussian over ``dim`` floats of which only some exist for each sample: the policy outputs a third
    parameter, ``mask [..., A]`` (1 where the entry acts, 0 where the env ignores it — an empty cell or a passive
    voxel of a controlled body, read from the observation), and the log-probability, entropy and KL sum over the
    masked entries only, so that PPO's ratio, entropy bonus and KL penalty see the actions that act and nothing else.
    The mask travels with the distribution's parameters (the rollout stores it, the minibatch reads it back)."""

    @property
    def param_dims(self) -> tuple[int, ...]:
        return (self.dim, self.dim, self.dim)

    def sample(self, params: Params, noise: torch.Tensor) -> torch.Tensor:
        mean, log_std, mask = params
        return torch.addcmul(mean, torch.exp(log_std), noise) * mask  # (the ignored entries: 0, not noise)

    def mode(self, params: Params) -> torch.Tensor:
        return params[0] * params[2]

    def log_prob(self, params: Params, actions: torch.Tensor) -> torch.Tensor:
        mean, log_std, mask = params
        return (gaussian_log_prob_entries(actions, mean, log_std) * mask).sum(-1)

    def entropy(self, params: Params) -> torch.Tensor:
        return (gaussian_entropy_entries(params[1]) * params[2]).sum(-1)

    def kl(self, old: Params, new: Params) -> torch.Tensor:
        (mean0, log_std0, mask), (mean1, log_std1, _) = old, new
        return (gaussian_kl_entries(mean0, log_std0, mean1, log_std1) * mask).sum(-1)

    def spec(self) -> dict[str, Any]:
        return {"kind": "masked_gaussian", "dim": self.dim}


@dataclass(frozen=True)
class MultiCategorical(ActionDistribution):
    """Independent categoricals, one per entry of ``nvec`` (choices 0 … nvec[k] − 1), their logits side by side."""

    nvec: tuple[int, ...]

    def __post_init__(self) -> None:
        nvec = tuple(int(n) for n in self.nvec)
        if not nvec or min(nvec) < 1:
            raise ValueError(f"a categorical needs at least one choice per entry, got nvec={self.nvec!r}")
        object.__setattr__(self, "nvec", nvec)

    @property
    def action_dim(self) -> int:
        return len(self.nvec)

    @property
    def param_dims(self) -> tuple[int, ...]:
        return (sum(self.nvec),)

    def _logits(self, params: Params) -> tuple[torch.Tensor, ...]:
        return params[0].split(list(self.nvec), dim=-1)

    def sample(self, params: Params, noise: torch.Tensor) -> torch.Tensor:
        return torch.stack([categorical_sample(z, noise[..., k]) for k, z in enumerate(self._logits(params))], -1)

    def mode(self, params: Params) -> torch.Tensor:
        return torch.stack([z.argmax(-1) for z in self._logits(params)], -1).to(params[0].dtype)

    def log_prob(self, params: Params, actions: torch.Tensor) -> torch.Tensor:
        return _total([categorical_log_prob(z, actions[..., k]) for k, z in enumerate(self._logits(params))])

    def entropy(self, params: Params) -> torch.Tensor:
        return _total([categorical_entropy(z) for z in self._logits(params)])

    def kl(self, old: Params, new: Params) -> torch.Tensor:
        return _total([categorical_kl(a, b) for a, b in zip(self._logits(old), self._logits(new), strict=True)])

    def spec(self) -> dict[str, Any]:
        return {"kind": "multi_categorical", "nvec": list(self.nvec)}


@dataclass(frozen=True)
class Categorical(MultiCategorical):
    """One categorical over ``n`` choices (Gymnasium's ``Discrete(n)``): a :class:`MultiCategorical` of one entry."""

    def __init__(self, n: int) -> None:
        super().__init__((n,))

    @property
    def n(self) -> int:
        return self.nvec[0]

    def __repr__(self) -> str:
        return f"Categorical(n={self.n})"

    def spec(self) -> dict[str, Any]:
        return {"kind": "categorical", "n": self.n}


@dataclass(frozen=True)
class Bernoulli(ActionDistribution):
    """``n`` independent bits (Gymnasium's ``MultiBinary(n)``), each 1 with probability sigmoid(logit)."""

    n: int

    def __post_init__(self) -> None:
        _check_size(self.n, "n")

    @property
    def action_dim(self) -> int:
        return self.n

    @property
    def param_dims(self) -> tuple[int, ...]:
        return (self.n,)

    def sample(self, params: Params, noise: torch.Tensor) -> torch.Tensor:
        return (noise < torch.sigmoid(params[0])).to(params[0].dtype)

    def mode(self, params: Params) -> torch.Tensor:
        return (params[0] > 0).to(params[0].dtype)

    def log_prob(self, params: Params, actions: torch.Tensor) -> torch.Tensor:
        return bernoulli_log_prob(params[0], actions)

    def entropy(self, params: Params) -> torch.Tensor:
        return bernoulli_entropy(params[0])

    def kl(self, old: Params, new: Params) -> torch.Tensor:
        return bernoulli_kl(old[0], new[0])

    def spec(self) -> dict[str, Any]:
        return {"kind": "bernoulli", "n": self.n}


def from_spec(spec: dict[str, Any] | ActionDistribution) -> ActionDistribution:
    """The distribution an :meth:`ActionDistribution.spec` describes (a distribution is returned as it is)."""
    if isinstance(spec, ActionDistribution):
        return spec
    kinds = {"gaussian": lambda s: DiagGaussian(int(s["dim"])), "categorical": lambda s: Categorical(int(s["n"])),
             "masked_gaussian": lambda s: MaskedDiagGaussian(int(s["dim"])),
             "multi_categorical": lambda s: MultiCategorical(tuple(s["nvec"])), "bernoulli": lambda s: Bernoulli(int(s["n"]))}
    if not isinstance(spec, dict) or spec.get("kind") not in kinds:
        raise ValueError(f"an action distribution spec is a dict with 'kind' one of {sorted(kinds)}, got {spec!r}")
    try:
        return kinds[spec["kind"]](spec)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"bad action distribution spec {spec!r} ({e})") from e


def for_space(space: Any) -> ActionDistribution:
    """The distribution for a Gymnasium action space: ``Box`` → :class:`DiagGaussian` over its flattened entries,
    ``Discrete`` → :class:`Categorical`, ``MultiDiscrete`` → :class:`MultiCategorical` (flattened), ``MultiBinary``
    → :class:`Bernoulli` (flattened). Any other space is refused, by name."""
    import gymnasium as gym  # (only this function needs Gymnasium)

    spaces = gym.spaces
    if isinstance(space, spaces.Box):
        return DiagGaussian(int(math.prod(space.shape)))
    if isinstance(space, spaces.Discrete):
        return Categorical(int(space.n))
    if isinstance(space, spaces.MultiDiscrete):
        return MultiCategorical(tuple(int(n) for n in space.nvec.reshape(-1)))
    if isinstance(space, spaces.MultiBinary):
        return Bernoulli(int(math.prod(space.shape)))
    raise ValueError(f"PPO has no action distribution for a {type(space).__name__} action space ({space}); it trains "
                     "Box, Discrete, MultiDiscrete and MultiBinary actions")


def head_distribution(distribution: Any, action_dim: int | None, network: str,
                      masked_hint: str = "") -> ActionDistribution:
    """The distribution a network with an action head over flat observations serves: ``distribution`` (an
    ``ActionDistribution`` or its ``spec()``; None: a Gaussian over ``action_dim``), ``action_dim`` agreeing with it
    when given. A ``MaskedDiagGaussian`` is refused (its mask comes from the observation: ``masked_hint`` says what to
    use instead)."""
    if distribution is None:
        if not isinstance(action_dim, int) or action_dim < 1:
            raise ValueError(f"action_dim must be a positive int, got {action_dim!r}")
        distribution = DiagGaussian(action_dim)
    dist = from_spec(distribution)
    if isinstance(dist, MaskedDiagGaussian):
        raise ValueError(f"{network} has no head for a MaskedDiagGaussian{masked_hint}")
    if action_dim is not None and action_dim != dist.action_dim:
        raise ValueError(f"action_dim {action_dim!r} disagrees with the {dist} ({dist.action_dim} numbers per action)")
    return dist


__all__ = ["head_distribution", "ActionDistribution", "Bernoulli", "Categorical", "DiagGaussian", "MaskedDiagGaussian", "MultiCategorical",
           "Params", "bernoulli_entropy", "bernoulli_kl", "bernoulli_log_prob", "categorical_entropy", "categorical_kl",
           "categorical_log_prob", "categorical_sample", "for_space", "from_spec", "gaussian_entropy",
           "gaussian_entropy_entries", "gaussian_kl", "gaussian_kl_entries", "gaussian_log_prob",
           "gaussian_log_prob_entries"]
