"""A direct voxel-grid genetic algorithm, the classic evosoro-style baseline: a genome is a grid ``[ρ, ρ, ρ]`` of
material indices, and a child is its parent's **body** (largest component) with ``mutation_voxels`` cells set to
another material — an empty cell touching the body gets one (set), a body voxel becomes empty (clear) or another
material (change). Selection as the sequence GA's (elitism + tournaments), no crossover.

Generation 0 is the final grids of N(0, I) action sequences (drawn exactly as :class:`~freeform.evolve.ga.SequenceGA`
draws its first generation, so with the same seed both start from the same designs).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from freeform.body import largest_component
from freeform.evolve.operators import Population, ranking, tournament


def touching(occupied: torch.Tensor) -> torch.Tensor:
    """``occupied [n, ρ, ρ, ρ]`` bool -> the occupied cells and their 6 face neighbours (inside the grid)."""
    out = occupied.clone()
    for dim in (1, 2, 3):
        size = occupied.shape[dim]
        out.narrow(dim, 1, size - 1).logical_or_(occupied.narrow(dim, 0, size - 1))
        out.narrow(dim, 0, size - 1).logical_or_(occupied.narrow(dim, 1, size - 1))
    return out


class GridGA(Population):
    """Population ``[N, ρ, ρ, ρ]`` uint8 (CPU). ``ask()`` gives the grids to score, ``tell(fitness [N])`` breeds."""

    genome = "grids"

    def __init__(self, population: int, actions: tuple[int, int], materials: int,
                 design: Callable[[torch.Tensor], torch.Tensor], *, elite: int = 2, tournament: int = 3,
                 mutation_voxels: int = 4, seed: int = 0) -> None:
        """``design(actions [N, T, A]) -> final grids [N, ρ, ρ, ρ] uint8`` makes generation 0 (no scoring) from
        action sequences of ``actions = (T, A)`` drawn from N(0, I)."""
        steps, action_dim = actions
        super().__init__(population, elite, seed)
        self.materials, self.tournament, self.mutation_voxels = materials, tournament, mutation_voxels
        first = torch.randn((population, steps, action_dim), generator=self.generator)  # as SequenceGA's generation 0
        self.population = design(first).to("cpu", torch.uint8)

    def tell(self, fitness: torch.Tensor) -> None:
        """Breed the next generation from the scores ``[N]`` of :meth:`ask`'s grids."""
        fitness = fitness.detach().to("cpu", torch.float64)
        pop, g, k = self.population, self.generator, self.materials
        n = self.size - self.elite
        elites = pop[ranking(fitness)[: self.elite]]
        parents = tournament(fitness, n, self.tournament, g)
        bodies = largest_component(pop[parents])  # [n, ρ, ρ, ρ]: a child starts as its parent's body
        region = touching(bodies != 0).reshape(n, -1)
        region[~region.any(dim=1)] = True  # an empty parent: anywhere
        # The cells to mutate, without repeats; a region smaller than mutation_voxels (a voxel in a corner) spills
        # onto the rest of the grid through the tiny weight.
        weights = region.to(torch.float32) + 1e-6
        m = min(self.mutation_voxels, weights.shape[1])
        cells = torch.multinomial(weights, m, replacement=False, generator=g)  # [n, m]
        shift = torch.randint(1, k, (n, m), generator=g)  # another material, uniformly (0 = clear)
        flat = bodies.reshape(n, -1).to(torch.int64)
        flat.scatter_(1, cells, (flat.gather(1, cells) + shift) % k)
        self.population = torch.cat([elites, flat.to(torch.uint8).reshape(bodies.shape)])


__all__ = ["GridGA", "touching"]
