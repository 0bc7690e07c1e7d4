"""The ``algo`` section of a run (``conf/algo/``): which optimiser designs the robots, and the evolutionary ones' settings.

``algo.name``: ``ppo`` (the default: the policy of ``freeform.agents``, configured by the ``agent`` section),
``ga`` (a genetic algorithm over the T design actions), ``cmaes`` (CMA-ES over the same sequences, through the
``cmaes`` library) or ``grid_ga`` (a genetic algorithm over voxel grids, the classic evosoro-style baseline); in a
control run, ``distill`` (DAgger from a bank of per-body teachers into one controller, ``freeform.agents.distill``). The
population of every evolutionary optimiser is ``env.num_envs`` designs, evaluated as one batch: a generation costs
what one PPO epoch costs in scored designs (one per environment).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from freeform.envs.symmetry import GROUPS
from freeform.learner import ALGORITHMS
from freeform.validation import is_int, is_number, require

CMA_VARIANTS = ("sep", "full")
ELITIST = ("ga", "grid_ga")
"""The learners that keep an elite of their population (``elite``: fewer than the population, ``env.num_envs``)."""


@dataclass
class AlgoConfig:
    """Which optimiser designs the robots; the fields after ``name`` are the evolutionary optimisers' (ignored by
    ``ppo``, whose settings are the ``agent`` section)."""

    name: str = "ppo"
    """``ppo`` | ``ga`` | ``cmaes`` | ``grid_ga`` | ``distill``."""
    elite: int = 2
    """ga, grid_ga: the best designs of a generation copied unchanged into the next (re-scored with it)."""
    tournament: int = 3
    """ga, grid_ga: a parent is the best of this many designs drawn at random (with replacement)."""
    crossover: float = 0.5
    """ga: probability that a child is the uniform crossover (each step from either parent) of two parents."""
    mutation_rate: float = 0.05
    """ga: probability that each of a child's T actions is resampled from N(0, I) — the paper's "random actions"."""
    mutation_voxels: int = 4
    """grid_ga: voxels of a child (in its parent's body or touching it) set to another material (0 clears)."""
    sigma: float = 1.0
    """cmaes: initial step size; the search starts at mean 0, so generation 0 samples N(0, σ²I) like the others."""
    variant: str = "sep"
    """cmaes: ``sep`` (diagonal covariance, linear in T·(3+k): 500 dims at the paper's volume size) or ``full``."""
    teacher: str | None = None
    """distill (``freeform.agents.distill``): the teacher run's directory or checkpoint (a control run with
    ``control.teachers`` = M, on this run's bodies and episode settings), whose teacher i mod M labels environment
    i's observations."""
    loss: str = "kl"
    """distill: ``kl`` (KL(teacher ‖ student) of the action distributions) or ``mse`` (the means' squared error)."""
    beta: float = 1.0
    """distill: round 0's probability that a step takes the teacher's action instead of the student's."""
    beta_decay: float = 0.5
    """distill: β of round r = beta · beta_decay^r."""
    buffer: int = 4
    """distill: rounds (epochs) of labelled observations the dataset aggregates."""
    symmetry: str = "none"
    """distill: ``ground`` — each regression sample turned about the vertical or mirrored at random, its label alike
    (a body turned is as good a body: ``freeform.envs.symmetry``); ``mirror`` — mirrored y → −y alone (keeps a wave
    along x); ``none``."""
    token_dropout: float = 0.0
    """distill: the probability that a regression sample's voxel is hidden from the rest of its body (a voxel-token
    student's attention and pooled summaries; ``freeform.agents.distill.DistillConfig.token_dropout``); 0: none."""

    def validate(self, key: str = "algo", num_envs: int | None = None, names: Sequence[str] = ALGORITHMS) -> None:
        """Raise ``ValueError`` naming ``<key>.<field>`` for a value out of range; ``names``: the learners a run can
        build (the registry ``freeform.learner.LEARNERS``, which a user's learner joins)."""
        require(self.name in names, f"{key}.name", f"one of {list(names)}", self.name)
        if num_envs is not None and self.name in ELITIST:  # (a population's elite: other learners ignore it)
            require(is_int(self.elite, 0) and self.elite < num_envs, f"{key}.elite",
                    f"an integer in [0, env.num_envs - 1 = {num_envs - 1}]", self.elite)
        else:
            require(is_int(self.elite, 0), f"{key}.elite", "an integer >= 0", self.elite)
        require(is_int(self.tournament, 1), f"{key}.tournament", "an integer >= 1", self.tournament)
        for name in ("crossover", "mutation_rate"):
            value = getattr(self, name)
            require(is_number(value) and 0 <= value <= 1, f"{key}.{name}", "a probability in [0, 1]", value)
        require(is_int(self.mutation_voxels, 1), f"{key}.mutation_voxels", "an integer >= 1", self.mutation_voxels)
        require(is_number(self.sigma) and self.sigma > 0, f"{key}.sigma", "> 0", self.sigma)
        require(self.variant in CMA_VARIANTS, f"{key}.variant", f"one of {list(CMA_VARIANTS)}", self.variant)
        require(self.symmetry in ("none", *GROUPS), f"{key}.symmetry", f"one of {['none', *GROUPS]}", self.symmetry)
        require(self.name != "distill" or (isinstance(self.teacher, str) and self.teacher != ""), f"{key}.teacher",
                "a teacher run's directory or checkpoint with algo.name=distill (train one with control.teachers=M)",
                self.teacher)
        if self.name == "cmaes" and num_envs is not None:
            require(num_envs >= 2, "env.num_envs", "an integer >= 2 with algo.name=cmaes (the population)", num_envs)


__all__ = ["ALGORITHMS", "AlgoConfig", "CMA_VARIANTS"]
