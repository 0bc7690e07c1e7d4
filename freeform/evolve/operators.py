"""What the genetic algorithms share: the population and its checkpointed state (:class:`Population`), ranking with
elitism, and tournaments. Pure torch on the CPU, drawing
only from the optimiser's own generator (so a seed and a checkpoint fix every choice)."""

from __future__ import annotations

from typing import Any

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


class Population:
    """A genetic algorithm's state: ``population`` (the genomes, ``[N, ...]`` on the CPU) and its own ``generator``.
    ``ask()`` gives the genomes to score; a subclass breeds in ``tell(fitness [N])``."""

    def __init__(self, size: int, elite: int, seed: int) -> None:
        if not 0 <= elite < size:
            raise ValueError(f"elite must be in [0, population - 1 = {size - 1}], got {elite}")
        self.size, self.elite = size, elite
        self.generator = torch.Generator().manual_seed(seed)
        self.population = torch.empty(0)

    def ask(self) -> torch.Tensor:
        """The generation to score."""
        return self.population

    def stats(self) -> dict[str, float]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {"population": self.population.clone(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        population = state["population"]
        if population.shape != self.population.shape:
            raise ValueError(f"the state's population has shape {list(population.shape)}, this run's is "
                             f"{list(self.population.shape)}")
        self.population = population.to(self.population.dtype).clone()
        self.generator.set_state(state["generator"])


__all__ = ["Population", "ranking", "tournament"]
