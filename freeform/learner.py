"""The Learner protocol: what the trainer (``freeform.run``) needs from an algorithm, and all it sees of one.

PPO (``freeform.agents.PPO``) and every evolutionary method (``freeform.evolve.Evolution``) implement it; a new
learner implements it and registers a builder (:func:`register_learner`, here below both the config and the app so
that ``freeform.config`` validates ``algo.name`` against the registry without importing ``freeform.run``), and the
trainer, the run
directory, TensorBoard, the design records, checkpoints, resume and preemption then work for it unchanged. The
trainer never asks which learner it drives, never sees a rollout, and takes its collectives from
``freeform.agents.distributed``, not from the learner.

An epoch is whatever the learner calls one (PPO: one rollout and one update; evolution: one generation). The
episodes an epoch finished are handed over in the design records' layout (``freeform.records``), as numpy arrays
(E = episodes, T = design steps, A = action size)::

    actions      [E, T, A] float32   the design actions (raw policy samples, or a genome)
    values       [E, T]    float32   the critic's V(s_t) (NaN where there is no critic)
    rewards      [E]       float32   the episode's return: what the task scored, never a scaled or shaped reward
    final_grids  [E, ρ, ρ, ρ] uint8  the designs
    metrics      {name: [E] float32} body metrics (``freeform.body``)
    yaw          [E]       int8      the placement the task scored, quarter turns (0: as designed; optional)
    infos        [dict]              the environment's own info dicts of the finishing steps (``bodies`` ...)
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol, runtime_checkable

Episodes = dict[str, Any]
"""An epoch's finished episodes (module docstring)."""


@runtime_checkable
class Learner(Protocol):
    """An algorithm the trainer can drive (module docstring). Data-parallel learners make ``train_epoch``,
    ``episodes`` and ``checkpoint`` collectives: every rank calls each once per epoch, in that order."""

    epoch: int
    """Epochs trained so far."""
    global_step: int
    """Environment steps so far, over all ranks (TensorBoard's x-axis)."""

    def train_epoch(self) -> dict[str, float]:
        """Train one epoch; its statistics by name (``freeform.logger.tag_for`` files them under TensorBoard tags;
        ``episode_reward_mean`` is the console's and the sweep summaries' learning curve)."""
        ...

    def episodes(self) -> Episodes | None:
        """The episodes the last epoch finished, over every rank (module docstring); None if none finished.
        Called once after every epoch."""
        ...

    def checkpoint(self) -> dict[str, Any]:
        """The learner's part of a run checkpoint: ``epoch``, ``global_step`` and its state under a key of its
        own (only tensors, numbers, strings and containers: checkpoints load with ``weights_only``)."""
        ...

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Continue from a run checkpoint whose learner part :meth:`checkpoint` wrote, exactly."""
        ...


ALGORITHMS = ("ppo", "ga", "cmaes", "grid_ga", "distill")
"""freeform's own learners (``algo.name``): PPO and the evolutionary baselines (``freeform.evolve``)."""

LearnerBuilder = Callable[[Any, Any, Any, tuple[int, int]], Learner]
"""``(cfg: TrainConfig, env, device: torch.device, envs: (lo, hi)) -> Learner``."""
LEARNERS: dict[str, LearnerBuilder] = {}
"""``algo.name`` -> its builder. freeform's own (:data:`ALGORITHMS`) are registered by
``freeform.run.build``; add one with :func:`register_learner`."""


def register_learner(*names: str) -> Callable[[LearnerBuilder], LearnerBuilder]:
    """Decorator: make ``algo.name=<name>`` (each of ``names``) build its learner with the decorated function."""

    def decorate(builder: LearnerBuilder) -> LearnerBuilder:
        for name in names:
            LEARNERS[name] = builder
        return builder

    return decorate


def learner_names() -> list[str]:
    """Every ``algo.name`` a run may give: freeform's own and every registered one (what ``freeform.config``
    validates against)."""
    return list(dict.fromkeys([*ALGORITHMS, *LEARNERS]))


__all__ = ["ALGORITHMS", "LEARNERS", "Episodes", "Learner", "LearnerBuilder", "learner_names", "register_learner"]
