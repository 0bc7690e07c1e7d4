"""A genetic algorithm over design-action sequences: a genome is the T raw actions ``[T, 3 + k]`` an episode of the
design environment applies, so it searches exactly the space the policy acts in.

One generation (``ask`` → score → ``tell``): the ``elite`` best genomes pass unchanged; every other child is a
tournament winner, with probability ``crossover`` uniformly crossed over steps with a second winner (each action
from either parent), then each of its T actions is resampled from N(0, I) with probability ``mutation_rate`` — the
paper's "random phylogenetic actions", not conditional on the state of the robot. Generation 0 is N(0, I) for every
action: the designs an untrained Gaussian policy of unit σ makes.
"""

from __future__ import annotations

import torch

from freeform.evolve.operators import Population, ranking, tournament


class SequenceGA(Population):
    """Population ``[N, T, A]`` float32 of action sequences (CPU). ``ask()`` gives the generation to score,
    ``tell(fitness [N])`` (higher is better) breeds the next."""

    genome = "actions"

    def __init__(self, population: int, steps: int, action_dim: int, *, elite: int = 2, tournament: int = 3,
                 crossover: float = 0.5, mutation_rate: float = 0.05, seed: int = 0) -> None:
        super().__init__(population, elite, seed)
        self.steps, self.action_dim = steps, action_dim
        self.tournament, self.crossover, self.mutation_rate = tournament, crossover, mutation_rate
        self.population = torch.randn((population, steps, action_dim), generator=self.generator)

    def tell(self, fitness: torch.Tensor) -> None:
        """Breed the next generation from the scores ``[N]`` of :meth:`ask`'s genomes."""
        fitness = fitness.detach().to("cpu", torch.float64)
        pop, g = self.population, self.generator
        n, steps = self.size - self.elite, self.steps
        elites = pop[ranking(fitness)[: self.elite]]
        # Every draw is made whatever the settings, so the random stream (and a resumed run) never depends on them.
        first = tournament(fitness, n, self.tournament, g)
        second = tournament(fitness, n, self.tournament, g)
        crossed = torch.rand(n, generator=g) < self.crossover  # [n]
        from_second = (torch.rand((n, steps), generator=g) < 0.5) & crossed[:, None]  # [n, T] uniform crossover
        mutated = torch.rand((n, steps), generator=g) < self.mutation_rate  # [n, T]
        fresh = torch.randn((n, steps, self.action_dim), generator=g)
        children = torch.where(from_second[..., None], pop[second], pop[first])
        children = torch.where(mutated[..., None], fresh, children)
        self.population = torch.cat([elites, children])


__all__ = ["SequenceGA"]
