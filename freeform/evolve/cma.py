"""CMA-ES over design-action sequences (the same genome as :mod:`freeform.evolve.ga`: T raw actions, flattened to
T·(3+k) numbers), through the ``cmaes`` library (CyberAgent's, pure numpy, ``pip install cmaes``).

``variant="sep"`` (the default) is sep-CMA-ES, a diagonal covariance: its cost per generation is linear in the
dimension (500 at the paper's volume size, 700 for locomotion), where full CMA-ES is cubic and needs far more
generations to learn a 500×500 covariance. The search starts at mean 0 with step ``sigma`` (1: generation 0 is
N(0, I), the same designs the GAs start from in distribution). Fitness is maximised (the library minimises −f).

Determinism and resuming: the library's own RNG is reseeded every generation from this optimiser's torch
generator, and its state is saved through its pickle protocol (``__getstate__``/``__setstate__``, numpy arrays as
tensors), so a checkpoint holds tensors and numbers only and a resumed run continues bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from freeform.evolve.config import CMA_VARIANTS


def _optimizer_class(variant: str) -> type:
    try:
        from cmaes import CMA, SepCMA
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ValueError(f"algo.name=cmaes needs the cmaes library: pip install 'freeform[evolve]' ({exc})") from exc
    if variant not in CMA_VARIANTS:
        raise ValueError(f"variant must be one of {list(CMA_VARIANTS)}, got {variant!r}")
    return SepCMA if variant == "sep" else CMA


def _to_saved(value: Any) -> Any:
    """numpy -> tensors and Python numbers (what ``torch.load(weights_only=True)`` reads back)."""
    if isinstance(value, np.ndarray):
        return torch.from_numpy(value.copy())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {k: _to_saved(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_to_saved(v) for v in value)
    return value


def _from_saved(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.numpy().copy()
    if isinstance(value, dict):
        return {k: _from_saved(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_from_saved(v) for v in value)
    return value


class CMAES:
    """A population of ``N`` action sequences ``[N, T, A]`` sampled from N(m, σ²C). ``ask()`` samples the
    generation, ``tell(fitness [N])`` (higher is better) updates m, σ and C."""

    genome = "actions"

    def __init__(self, population: int, steps: int, action_dim: int, *, sigma: float = 1.0, variant: str = "sep",
                 seed: int = 0) -> None:
        if population < 2:
            raise ValueError(f"population must be >= 2, got {population}")
        self.size, self.steps, self.action_dim, self.variant = population, steps, action_dim, variant
        self._class = _optimizer_class(variant)
        self.optimizer = self._class(mean=np.zeros(steps * action_dim), sigma=float(sigma), population_size=population,
                                     seed=seed)
        # cmaes allocates its fitness history with np.empty and reads it only once every slot is written: zero it so
        # the state (and a checkpoint) holds no uninitialised memory and equal runs have equal states.
        history = getattr(self.optimizer, "_funhist_values", None)
        if isinstance(history, np.ndarray):
            history.fill(0.0)
        self.generator = torch.Generator().manual_seed(seed)
        self._asked: np.ndarray | None = None

    def ask(self) -> torch.Tensor:
        """Sample the generation, ``[N, T, A]`` float32."""
        self.optimizer.reseed_rng(int(torch.randint(0, 2**31 - 1, (1,), generator=self.generator)))
        self._asked = np.stack([self.optimizer.ask() for _ in range(self.size)])  # [N, T·A] float64
        return torch.from_numpy(self._asked).to(torch.float32).reshape(self.size, self.steps, self.action_dim)

    def tell(self, fitness: torch.Tensor) -> None:
        """Update the search distribution from the scores ``[N]`` of the last :meth:`ask`."""
        if self._asked is None:
            raise ValueError("tell() before ask()")
        values = fitness.detach().to("cpu", torch.float64).tolist()
        self.optimizer.tell([(x, -v) for x, v in zip(self._asked, values, strict=True)])
        self._asked = None

    @property
    def mean(self) -> torch.Tensor:
        """The search distribution's mean ``[T, A]`` (float64)."""
        return torch.from_numpy(self.optimizer.mean.copy()).reshape(self.steps, self.action_dim)

    @property
    def sigma(self) -> float:
        return float(self.optimizer._sigma)  # the library keeps it private; read for logging only

    def stats(self) -> dict[str, float]:
        return {"evolution/sigma": self.sigma}

    def state_dict(self) -> dict[str, Any]:
        return {"variant": self.variant, "cma": _to_saved(self.optimizer.__getstate__()),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["variant"] != self.variant:
            raise ValueError(f"the state is of algo.variant={state['variant']!r}, this run's is {self.variant!r}")
        optimizer = self._class.__new__(self._class)
        optimizer.__setstate__(_from_saved(state["cma"]))
        if optimizer.dim != self.steps * self.action_dim or optimizer.population_size != self.size:
            raise ValueError(f"the state's CMA-ES has {optimizer.dim} dimensions and population "
                             f"{optimizer.population_size}; this run's: {self.steps * self.action_dim}, {self.size}")
        self.optimizer = optimizer
        self.generator.set_state(state["generator"])


__all__ = ["CMAES"]
