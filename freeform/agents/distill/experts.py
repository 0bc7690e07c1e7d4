"""Experts chosen by trial, trained as such: hard EM over K controllers for M bodies.

One controller for every body averages gaits that do not mix; the best of several by one trial each
(``freeform-control fit``) is only as good as the several. Hard EM trains the several for that very choice:

- **E-step** (assignment): every expert is tried on every body (one episode, mean command); body m goes to the
  expert that moved it furthest, ``argmax_k moves[k, m]`` — the rule ``fit`` chooses by;
- **M-step** (refit): each trainable expert is distilled from the teachers of the bodies it won (a body's teacher:
  its own per-body controller); an expert that won no body, or a fixed one (the hand-set wave), stays as it is;
- repeated until the assignment is a fixed point (a round that reassigns no body) or ``rounds`` refits.

With moves the negative squared distance between a point and a centre, and a refit that is the mean of the points
won, this is Lloyd's k-means (``tests/test_experts.py`` checks it against scipy's). The loop here knows nothing of
bodies or controllers: ``trial`` and ``refit`` are the caller's (``lab.experts``: trials by
``freeform.control.fit.trials``, refits by ``algo=distill`` from a teacher run's chosen teachers).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Generic, NamedTuple, TypeVar

import numpy as np

Expert = TypeVar("Expert")


def assign(moves: np.ndarray) -> np.ndarray:
    """Each body's expert ``[M]`` int: the one whose trial moved it furthest, of ``moves`` ``[K, M]`` (a tie goes
    to the earlier expert, as ``fit``'s)."""
    moves = np.asarray(moves, dtype=float)
    if moves.ndim != 2 or not moves.size:
        raise ValueError(f"moves must be [experts, bodies], each at least one, got shape {moves.shape}")
    if not np.isfinite(moves).all():
        raise ValueError("moves must be finite: a trial that diverged cannot be ranked (nan or inf in moves)")
    return moves.argmax(0)


class Round(NamedTuple):
    """One E-step: the trial moves ``[K, M]`` of the experts as they stood, and the assignment ``[M]`` they give."""

    moves: np.ndarray
    assignment: np.ndarray


class HardEM(NamedTuple, Generic[Expert]):
    """Hard EM's outcome: the experts, the last assignment, every E-step in order (the first before any refit),
    and whether it ended at a fixed point (else it ran out of ``rounds``)."""

    experts: list[Expert]
    assignment: np.ndarray
    history: list[Round]
    fixed_point: bool


def hard_em(experts: Sequence[Expert], trial: Callable[[list[Expert]], np.ndarray],
            refit: Callable[[int, Expert, np.ndarray], Expert], rounds: int,
            fixed: Sequence[bool] | None = None) -> HardEM[Expert]:
    """Hard EM from ``experts`` (module docstring). ``trial(experts) -> moves [K, M]``; ``refit(k, expert,
    bodies) -> expert`` trains expert k on the bodies it won (``bodies``: their indices, never empty); ``fixed[k]``:
    expert k is never refit. Refits at most ``rounds`` times (0: the assignment of ``experts`` alone)."""
    experts = list(experts)
    k = len(experts)
    fixed = [False] * k if fixed is None else list(fixed)
    if k < 1 or len(fixed) != k:
        raise ValueError(f"hard EM needs at least one expert and one 'fixed' flag each, got {k} experts and "
                         f"{len(fixed)} flags")
    if rounds < 0:
        raise ValueError(f"rounds must be >= 0, got {rounds}")
    history = [_e_step(trial, experts)]
    for _ in range(rounds):
        won = history[-1].assignment
        experts = [e if fixed[i] or not (won == i).any() else refit(i, e, np.flatnonzero(won == i))
                   for i, e in enumerate(experts)]
        history.append(_e_step(trial, experts))
        if np.array_equal(history[-1].assignment, won):
            return HardEM(experts, won, history, True)
    return HardEM(experts, history[-1].assignment, history, False)


def _e_step(trial: Callable[[list[Expert]], np.ndarray], experts: list[Expert]) -> Round:
    moves = np.asarray(trial(experts), dtype=float)
    if moves.ndim != 2 or moves.shape[0] != len(experts):
        raise ValueError(f"trial must return moves [experts={len(experts)}, bodies], got shape {moves.shape}")
    return Round(moves, assign(moves))


__all__ = ["HardEM", "Round", "assign", "hard_em"]
