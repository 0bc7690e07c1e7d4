"""``python -m experiments.rl_vs_evolution`` on a tiny real sweep (PPO and the GA, two seeds each, through the app):
the cost axis counts the designs each run scored, the curves and the summary equal an independent recomputation
from the records, and the figure, CSVs and provenance are written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli as cli  # tests/helpers.py
from helpers import tiny

from experiments import common, rl_vs_evolution
from freeform.records import iter_records

pytest.importorskip("matplotlib")


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("rve") / "sweep"
    with pytest.MonkeyPatch.context() as mp:
        cli(mp, "-m", *tiny("env.num_envs=6", "trainer.checkpoint_every=0"), "trainer.epochs=4", "algo=ppo,ga",
            "seed=0,1", f"hydra.sweep.dir={root}")
    return root


def test_comparison_counts_designs_and_matches_the_records(sweep: Path, tmp_path: Path) -> None:
    out = rl_vs_evolution.main([str(sweep), "--out", str(tmp_path), "--budget", "18"])
    for name in ("csv", "summary_csv", "png", "pdf"):
        assert out[name].is_file() and out[name].stat().st_size > 0, name
    prov, cols = common.read_csv(out["csv"])
    assert prov["runs"] == "4" and prov["budget_designs"] == "18"
    for method in ("ppo", "ga"):
        rows = cols["method"] == method
        np.testing.assert_array_equal(cols["designs"][rows], [6, 12, 18, 24])  # 6 designs an epoch, either way
        runs = sorted(sweep.glob(f"algo={method},seed=*"))
        maxima = np.array([[r.rewards.max() for r in iter_records(run)] for run in runs])  # [seeds, epochs]
        best = np.maximum.accumulate(maxima, axis=1)
        np.testing.assert_allclose(cols["best"][rows], best.mean(axis=0), rtol=1e-5)
        means = np.array([[r.rewards.mean() for r in iter_records(run)] for run in runs])
        np.testing.assert_allclose(cols["mean_raw"][rows], means.mean(axis=0), rtol=1e-5)
        # At 18 designs (epoch 2, the third): the population mean over the last 5 epochs (here epochs 0-2) and the
        # best so far, across the two seeds.
        _, summary = common.read_csv(out["summary_csv"])
        row = list(summary["method"]).index(method)
        assert summary["designs"][row] == 18
        assert summary["population_mean"][row] == pytest.approx(means[:, :3].mean(axis=1).mean(), rel=1e-5)
        assert summary["best_so_far"][row] == pytest.approx(best[:, 2].mean(), rel=1e-5)
        sd = best[:, 2].std(ddof=1)
        assert summary["best_so_far_band"][row] == pytest.approx(common.Z_99 * sd / np.sqrt(2), rel=1e-5, abs=1e-6)


def test_cost_of_dense_rewards_counts_the_partial_bodies() -> None:
    """Dense rewards every k steps score the partial bodies at steps k, 2k, … < T as well as the final one:
    DenseDesignReward's own calls to the task, counted."""
    import torch

    from freeform.envs import DesignEnv, EnvConfig, VolumeTask
    from freeform.envs.dense import DenseDesignReward

    class Counting(VolumeTask):
        calls = 0

        def reward(self, final_grids, bodies=None):  # type: ignore[override]
            Counting.calls += len(final_grids)
            return super().reward(final_grids, bodies)

    for steps, every in ((10, 3), (10, 5), (7, 1), (5, 10)):
        Counting.calls = 0
        env = DenseDesignReward(DesignEnv(2, EnvConfig(resolution=6, steps=steps),
                                          materials=2, task=Counting()), every)
        env.reset()
        for _ in range(steps):
            env.step(torch.randn(2, env.action_dim))
        config = {"env": {"steps": steps, "dense_every": every}}
        assert Counting.calls == 2 * rl_vs_evolution.designs_per_episode(config), (steps, every)
        assert rl_vs_evolution.method_of({"algo": {"name": "ppo"}, **config}) == f"ppo+dense({every})"
    assert rl_vs_evolution.designs_per_episode({"env": {"steps": 100}}) == 1
    assert rl_vs_evolution.method_of({"env": {}}) == "ppo"


def test_population_mean_at_the_budget_averages_only_the_last_epochs(sweep: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """With a window shorter than the run (2 epochs), the mean at 24 designs (epoch 3) is epochs 2-3's, not 0-3's."""
    monkeypatch.setattr(rl_vs_evolution, "LAST_EPOCHS", 2)
    out = rl_vs_evolution.main([str(sweep), "--out", str(tmp_path), "--budget", "24"])
    _, summary = common.read_csv(out["summary_csv"])
    for method in ("ppo", "ga"):
        runs = sorted(sweep.glob(f"algo={method},seed=*"))
        means = np.array([[r.rewards.mean() for r in iter_records(run)] for run in runs])  # [seeds, 4 epochs]
        row = list(summary["method"]).index(method)
        assert summary["population_mean"][row] == pytest.approx(means[:, 2:4].mean(axis=1).mean(), rel=1e-5)
