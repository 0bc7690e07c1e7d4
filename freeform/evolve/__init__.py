"""Evolutionary design search on the design space, tasks and batched simulator PPO uses — the baselines of
``freeform-train algo=ga|cmaes|grid_ga`` (``docs/experiments.md``, "RL against evolution").

- :class:`SequenceGA` — a genetic algorithm over the T design actions (resampling mutation from N(0, I), uniform
  crossover over steps, elitism, tournaments);
- :class:`CMAES` — (sep-)CMA-ES over the same sequences, through the ``cmaes`` library;
- :class:`GridGA` — a direct voxel-grid GA (set, clear or change voxels of the parent's body);
- :class:`Evolution` — any of them behind the trainer's ``train_epoch()/state_dict()/checkpoint()`` surface;
  :func:`build_evolution` makes one from a run's config.
"""

from __future__ import annotations

from typing import Any

from freeform.envs.untrained import design_grids, untrained_design_bodies, untrained_design_grids
from freeform.evolve.cma import CMAES
from freeform.evolve.config import ALGORITHMS, AlgoConfig
from freeform.evolve.ga import SequenceGA
from freeform.evolve.grid_ga import GridGA
from freeform.evolve.runner import Evolution


def build_evolution(algo: AlgoConfig, env: Any, seed: int) -> Evolution:
    """The evolutionary optimiser ``algo.name`` over ``env`` (a ``DesignEnv``; population ``env.num_envs``),
    seeded by ``seed``."""
    algo.validate("algo", env.num_envs)
    n, steps, dim = env.num_envs, env.steps, env.action_dim
    optimizer: Any
    if algo.name == "ga":
        optimizer = SequenceGA(n, steps, dim, elite=algo.elite, tournament=algo.tournament, crossover=algo.crossover,
                               mutation_rate=algo.mutation_rate, seed=seed)
    elif algo.name == "cmaes":
        optimizer = CMAES(n, steps, dim, sigma=algo.sigma, variant=algo.variant, seed=seed)
    elif algo.name == "grid_ga":
        optimizer = GridGA(n, (steps, dim), env.materials, lambda actions: design_grids(env, actions), elite=algo.elite,
                           tournament=algo.tournament, mutation_voxels=algo.mutation_voxels, seed=seed)
    else:
        raise ValueError(f"algo.name must be one of {[a for a in ALGORITHMS if a not in ('ppo', 'distill')]} here, "
                         f"got {algo.name!r}")
    return Evolution(env, optimizer, algo.name)


__all__ = ["ALGORITHMS", "AlgoConfig", "CMAES", "Evolution", "GridGA", "SequenceGA", "build_evolution",
           "design_grids", "untrained_design_bodies", "untrained_design_grids"]
