"""experiments/: the shared statistics against independent truth, and a tiny variant of every figure command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from experiments import common


# ---------------------------------------------------------------------------------------------------- statistics
def test_band_is_the_99_percent_normal_interval_of_the_mean():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, size=(5, 7))
    mean, half = common.mean_band(x, axis=0)
    # scipy: the normal quantile and the standard error of the mean (Bessel-corrected sd / √n).
    z = stats.norm.ppf(0.995)
    np.testing.assert_allclose(mean, x.mean(0))
    np.testing.assert_allclose(half, z * stats.sem(x, axis=0), rtol=1e-4)


def test_band_of_one_trial_is_zero_and_nans_are_skipped():
    mean, half = common.mean_band(np.array([[1.0, 2.0]]), axis=0)
    np.testing.assert_array_equal(half, [0.0, 0.0])
    mean, half = common.mean_band(np.array([[1.0, 2.0], [3.0, np.nan]]), axis=0)
    np.testing.assert_allclose(mean, [2.0, 2.0])
    assert half[1] == 0.0 and half[0] > 0


def test_moving_average_is_a_centred_five_epoch_window_cut_at_the_ends():
    x = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0])
    # Hand-worked: window [i-2, i+2] ∩ [0, 5].
    expect = [np.mean([0, 10, 20]), np.mean([0, 10, 20, 30]), np.mean([0, 10, 20, 30, 40]),
              np.mean([10, 20, 30, 40, 50]), np.mean([20, 30, 40, 50]), np.mean([30, 40, 50])]
    np.testing.assert_allclose(common.moving_average(x), expect)
    np.testing.assert_allclose(common.moving_average(x, 0), x)
    # Batched over leading axes, NaNs skipped inside a window.
    y = np.stack([x, x * 2])
    np.testing.assert_allclose(common.moving_average(y)[1], 2 * np.asarray(expect))
    np.testing.assert_allclose(common.moving_average(np.array([1.0, np.nan, 3.0]), 1), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="half_window"):
        common.moving_average(x, -1)


def test_across_trials_smooths_mean_and_band_together():
    per_trial = np.array([[0.0, 1, 2, 3, 4], [2.0, 3, 4, 5, 6]])
    c = common.across_trials(per_trial)
    np.testing.assert_allclose(c.raw_mean, [1, 2, 3, 4, 5])
    np.testing.assert_allclose(c.mean, common.moving_average(np.array([1.0, 2, 3, 4, 5])))
    # Constant spread: sd = √2 everywhere, so the band is 2.576·√2/√2 on both sides.
    np.testing.assert_allclose(c.upper - c.mean, common.Z_99)
    np.testing.assert_array_equal(c.n_trials, [2] * 5)


def test_stack_ragged_pads_with_nan():
    s = common.stack_ragged([np.array([1.0, 2.0]), np.array([3.0])])
    assert s.shape == (2, 2) and np.isnan(s[1, 1]) and s[1, 0] == 3.0


# ---------------------------------------------------------------------------------------------------- runs, output
def _fake_run(d: Path, **info) -> Path:
    d.mkdir(parents=True)
    (d / common.RUN_INFO).write_text(json.dumps(info))
    return d


def test_find_runs_searches_sweeps_and_names_missing_paths(tmp_path):
    a = _fake_run(tmp_path / "sweep" / "0", seed=0)
    b = _fake_run(tmp_path / "sweep" / "1", seed=1)
    assert common.find_runs([tmp_path / "sweep"]) == [a.resolve(), b.resolve()]
    assert common.find_runs([a, a]) == [a.resolve()]
    with pytest.raises(ValueError, match="paths"):
        common.find_runs([tmp_path / "nope"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no run directory"):
        common.find_runs([tmp_path / "empty"])


def test_provenance_merges_runs_and_csv_round_trips(tmp_path):
    a = _fake_run(tmp_path / "0", versions={"freeform": "0.1.0", "torch": "2.13", "taichi": "1.7.4"},
                  device="cpu", git_commit="abc")
    b = _fake_run(tmp_path / "1", versions={"freeform": "0.1.0", "torch": "2.13", "taichi": "1.7.4"},
                  device="cuda:0", git_commit="abc")
    prov = common.provenance([a, b])
    assert prov["torch"] == "2.13" and prov["device"] == "cpu | cuda:0" and prov["git_commit"] == "abc"
    assert prov["runs"] == "2"
    path = common.write_csv(tmp_path / "x.csv", {"epoch": [0, 1], "mean": [0.5, 1.25]}, prov)
    prov2, cols = common.read_csv(path)
    assert prov2 == prov
    np.testing.assert_allclose(cols["mean"], [0.5, 1.25])
    with pytest.raises(ValueError, match="columns"):
        common.write_csv(tmp_path / "y.csv", {"a": [1], "b": [1, 2]})
