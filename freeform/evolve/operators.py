"""Selection shared by the genetic algorithms: ranking with elitism, and tournaments. Pure torch on the CPU, drawing
only from the optimiser's own generator (so a seed and a checkpoint fix every choice)."""

from __future__ import annotations

import torch


def ranking(fitness: torch.Tensor) -> torch.Tensor:
    """Indices of ``fitness [N]`` from best to worst; equal fitness keeps the lower index first (deterministic)."""
    return torch.sort(fitness, descending=True, stable=True).indices


def tournament(fitness: torch.Tensor, count: int, size: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` parents ``[count]`` int64: each the best of ``size`` designs drawn uniformly with replacement (ties:
    the first drawn). Selection pressure grows with ``size``; ``size = 1`` is uniform selection."""
    entrants = torch.randint(0, len(fitness), (count, size), generator=generator)  # [count, size]
    best = torch.argmax(fitness[entrants], dim=1)  # first maximum: the earliest entrant among equals
    return entrants.gather(1, best[:, None]).squeeze(1)


__all__ = ["ranking", "tournament"]
