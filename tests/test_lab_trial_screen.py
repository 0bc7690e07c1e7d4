"""``lab.trial_screen``: choosing a body's candidate by a short trial, or by a short screen and a finish."""

from __future__ import annotations

import numpy as np
import pytest

from lab.trial_screen import rows_of, screened


def after() -> np.ndarray:
    """``[D=2, C=3, M=2]``: each candidate's move after decision 1 and 2 on two bodies. Body 0: candidate 0 leads
    after one decision (1.0) and ends last (1.1); candidate 2 is second early (0.8) and ends best (3.0). Body 1: the
    early order is the final one (candidate 1 best)."""
    return np.array([[[1.0, 0.1], [0.2, 0.9], [0.8, 0.3]],
                     [[1.1, 0.2], [2.0, 2.5], [3.0, 0.4]]])


def test_a_short_trial_keeps_its_leader_and_a_finish_among_the_best_k_recovers_the_whole_episodes_choice() -> None:
    a = after()
    assert screened(a, 1, 1).tolist() == [0, 1]      # (the early leader, wrong on body 0)
    assert screened(a, 1, 2).tolist() == [2, 1]      # (0 and 2 finish on body 0: 2 wins)
    assert screened(a, 2, 1).tolist() == [2, 1]      # (the whole episode: fit's choice)
    assert screened(a, 1, 3).tolist() == [2, 1]
    many = np.zeros((2, 40, 1))                      # (an early tie among many: the earliest, as fit's; 40 candidates,
    many[0, 5:, 0] = 1.0                             # past the lengths a plain sort keeps in order by chance)
    many[1, :, 0] = np.arange(40.0)
    assert screened(many, 1, 1).tolist() == [5] and screened(many, 1, 3).tolist() == [7]


def test_each_rules_row_counts_its_physics_and_pairs_its_moves_with_fits_choice() -> None:
    rows = rows_of(after(), reference=np.array([3.0, 2.5]), rules=[(2, 1), (1, 1), (1, 2)])
    full, short, finished = rows
    assert full["episodes_a_body"] == 3 and full["fraction"] == pytest.approx(1.0) and full["minus_full"] == 0.0
    # one decision of three candidates (1.5 episodes), body 0 left with 1.1 instead of 3.0
    assert short["episodes_a_body"] == 1.5 and short["mean_move"] == pytest.approx((1.1 + 2.5) / 2)
    assert short["minus_full"] == pytest.approx(-0.95) and short["bodies_worse"] == 1
    assert short["fraction"] == pytest.approx(3.6 / 5.5)
    assert finished["episodes_a_body"] == 3.5 and finished["minus_full"] == 0.0 and finished["bodies_worse"] == 0
