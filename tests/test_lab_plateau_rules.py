"""``lab.plateau_rules``: where a window rule stops a reference's evaluated curve, against the analytic stop on an
exponential approach."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from freeform.tables import write_rows
from lab.plateau_rules import first_stop, main


def test_a_window_rule_stops_an_exponential_where_the_analytic_window_gain_falls_under_the_gain(tmp_path) -> None:
    """y = a − b·exp(−t/τ) every 10 epochs: the rule stops at the first point where the mean of the last W epochs'
    points is less than g above the W before, found here by evaluating the closed form window by window (not through
    ``plateaued``). The measured curve (the same points to epoch 300, with a
    dip at 120 that a window of 20 reads as flat) stops earlier for W = 20, as the steering curve did."""
    a, b, tau = 4.0, 3.0, 60.0
    t = np.arange(0, 301, 10)
    y = a - b * np.exp(-t / tau)

    def analytic(window: int, gain: float) -> int:
        for end in range(2 * window, 3001, 10):
            last = np.mean([a - b * math.exp(-s / tau) for s in range(end - window + 10, end + 1, 10)])
            before = np.mean([a - b * math.exp(-s / tau) for s in range(end - 2 * window + 10, end - window + 1, 10)])
            if last - before < gain * before:
                return end
        raise AssertionError("never")

    for window in (20, 40):
        assert first_stop(np.arange(10, 3001, 10), a - b * np.exp(-np.arange(10, 3001, 10) / tau), window,
                          0.02) == analytic(window, 0.02)
    dipped = y.copy()
    dipped[12] = dipped[10]  # (epoch 120 back to epoch 100's value)
    # (at 130 the window holds the dip: (y100 + y130) / 2 over (y100 + y110) / 2 is +1.9 %)
    assert first_stop(t, dipped, 20, 0.02) == 130 < first_stop(t, y, 20, 0.02)
    folder = tmp_path / "ref"
    folder.mkdir()
    write_rows(folder / "curve.csv", [{"epoch": int(e), "mean_command": float(v)} for e, v in zip(t, y, strict=True)])
    write_rows(folder / "asymptote.csv", [{"asymptote": a, "b": b, "tau_epochs": tau, "first_epoch": 0}])
    main([str(folder), "--windows", "20", "--gains", "0.02", "--out", str(tmp_path / "rules.csv")])
    row = next(csv.DictReader(open(tmp_path / "rules.csv")))
    stop = analytic(20, 0.02)
    assert int(row["stops_fitted"]) == stop
    assert float(row["share_fitted"]) == pytest.approx(1 - b / a * math.exp(-stop / tau))
    assert int(row["stops_measured"]) == stop  # (the measured curve is the fitted one, to its end at 300)
    with pytest.raises(SystemExit):
        main([str(folder), "--windows", "25", "--out", str(tmp_path / "other.csv")])
