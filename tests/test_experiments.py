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


def test_the_paired_band_is_students_t_over_the_bodies_and_one_body_has_none():
    """scipy's t interval (n − 1 degrees of freedom) for per-body differences; a one-body table (an exported
    teacher on its own body) gives its difference with half-width 0 instead of failing."""
    d = np.array([0.3, -0.1, 0.2, 0.5, 0.0])
    mean, half = common.paired_band(d)
    low, high = stats.t.interval(0.99, len(d) - 1, loc=d.mean(), scale=stats.sem(d))
    assert mean == pytest.approx(d.mean()) and half == pytest.approx((high - low) / 2, rel=1e-9)
    assert common.paired_band(np.array([0.4])) == (0.4, 0.0)
    assert common.paired_band(np.append(d, np.nan)) == (mean, half)  # (a missing body: not counted, df as without)
    with pytest.raises(ValueError, match="at least one"):
        common.paired_band(np.zeros(0))


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


# ---------------------------------------------------------------------------------------------------- runs, output
def _fake_run(d: Path, **info) -> Path:
    d.mkdir(parents=True)
    (d / common.RUN_INFO).write_text(json.dumps(info))
    return d


def test_rows_round_trip_and_an_empty_table_is_refused_leaving_the_file(tmp_path):
    rows = [{"a": 1, "b": 2.5}, {"a": 3, "c": "x"}]
    path = common.write_rows(tmp_path / "t.csv", rows)
    assert common.read_rows(path) == [{"a": "1", "b": "2.5", "c": ""}, {"a": "3", "b": "", "c": "x"}]
    with pytest.raises(ValueError, match="no rows to write"):
        common.write_rows(path, [])
    assert len(common.read_rows(path)) == 2


def test_find_runs_searches_sweeps_and_names_missing_paths(tmp_path):
    a = _fake_run(tmp_path / "sweep" / "0", seed=0)
    b = _fake_run(tmp_path / "sweep" / "1", seed=1)
    assert common.find_runs([tmp_path / "sweep"]) == [a.resolve(), b.resolve()]
    assert common.find_runs([a, a]) == [a.resolve()]
    (tmp_path / "linked").mkdir()
    (tmp_path / "linked" / "seed=0").symlink_to(a)  # a sweep assembled from links to runs
    assert common.find_runs([tmp_path / "linked"]) == [a.resolve()]
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


# ---------------------------------------------------------------------------------------------------- fixtures
def _record_fixture(root: Path, seeds=(0, 1, 2), epochs: int = 6, episodes: int = 8, rho: int = 6,
                    materials: int = 4, steps: int = 5) -> list[Path]:
    """Runs written with freeform.records: random grids that fill up with the epoch, reward = body volume."""
    import torch

    from freeform.body import metrics
    from freeform.records import EpochRecord, write_record

    runs = []
    for seed in seeds:
        run = _fake_run(root / f"seed={seed}", seed=seed, freeform="0.1.0", torch="2.13", taichi="1.7.4",
                        device="cpu", git_commit="f" * 40)
        g = torch.Generator().manual_seed(seed)
        for e in range(epochs):
            fill = 0.15 + 0.1 * e
            occupied = torch.rand(episodes, rho, rho, rho, generator=g) < fill
            grids = (occupied * torch.randint(1, materials, occupied.shape, generator=g)).to(torch.uint8)
            m = {k: v.numpy() for k, v in metrics(grids).items()}
            write_record(run, EpochRecord(
                epoch=e, global_step=(e + 1) * episodes * steps,
                actions=torch.randn(episodes, steps, 3 + materials, generator=g).numpy(),
                final_grids=grids.numpy(), rewards=m["volume"].astype(np.float32),
                values=torch.randn(episodes, steps, generator=g).numpy(), metrics=m))
        runs.append(run)
    return runs


@pytest.fixture(scope="module")
def record_runs(tmp_path_factory) -> list[Path]:
    return _record_fixture(tmp_path_factory.mktemp("sweep"))


def test_load_trial_means_each_epoch(record_runs):
    from freeform.records import iter_records

    t = common.load_trial(record_runs[0])
    recs = list(iter_records(record_runs[0]))
    np.testing.assert_array_equal(t.epochs, np.arange(6))
    np.testing.assert_allclose(t.reward, [r.rewards.mean() for r in recs], rtol=1e-6)
    np.testing.assert_allclose(t.metrics["lcc_ratio"], [r.metrics["lcc_ratio"].mean() for r in recs], rtol=1e-6)
    assert t.seed == 0


def test_volume_figure_from_records(record_runs, tmp_path):
    from experiments import volume

    out = volume.main([str(record_runs[0].parent), "--out", str(tmp_path)])
    for key in ("png", "pdf", "reward_csv", "bodies_csv"):
        assert out[key].is_file() and out[key].stat().st_size > 0
    prov, cols = common.read_csv(out["reward_csv"])
    assert prov["git_commit"] == "f" * 40 and prov["runs"] == "3"
    # The curve's raw mean is the mean over trials of each trial's epoch mean (independent recomputation).
    trials = [common.load_trial(r) for r in record_runs]
    np.testing.assert_allclose(cols["reward_raw_mean"], np.mean([t.reward for t in trials], axis=0), rtol=1e-5)
    _, bodies = common.read_csv(out["bodies_csv"])
    assert list(bodies["label"]) == list("ABCDEF")
    np.testing.assert_array_equal(bodies["epoch"], [0, 0, 1, 2, 3, 5])  # round(f·5) for the paper's fractions
    # Each drawn body is the episode closest to its epoch's mean reward, over all trials' episodes.
    from freeform.records import read_record, record_path

    for epoch, reward, target in zip(bodies["epoch"], bodies["reward"], bodies["epoch_mean_reward"], strict=True):
        pooled = np.concatenate([read_record(record_path(r, int(epoch))).rewards for r in record_runs])
        assert abs(reward - target) == pytest.approx(np.abs(pooled - target).min(), abs=1e-4)


def test_design_diversity_compares_the_first_and_last_windows_of_a_run(tmp_path):
    """Analytic spread: one body placed anywhere is one design; two bodies differing in c of the 216 cells, two
    copies each, differ in 4 of the 6 pairs, so their distance is (4 / 6) * c / 216."""
    from experiments import design_diversity
    from freeform.records import EpochRecord, write_record

    def body(x: int, y: int, extra: int = 0) -> np.ndarray:
        g = np.zeros((6, 6, 6), np.uint8)
        g[x:x + 2, y:y + 3, 0:2] = 3
        g[x, y, 2:2 + extra] = 1  # a mast of `extra` cells: the second body's difference
        return g

    run = tmp_path / "run"
    windows = [[body(0, 0), body(3, 2)], [body(1, 1), body(2, 3)],  # the first two epochs: one design, moved
               [body(0, 0), body(0, 0, 3)], [body(1, 0), body(0, 2, 3)]]  # the last two: two designs, c = 3
    for e, grids in enumerate(windows):
        grids = np.stack(grids)
        write_record(run, EpochRecord(epoch=e, global_step=e, actions=np.zeros((2, 1, 1), np.float32),
                                      final_grids=grids, rewards=np.array([e, e + 1], np.float32),
                                      values=np.zeros((2, 1), np.float32),
                                      metrics={"volume": (grids > 0).sum((1, 2, 3)).astype(np.float32)}))
    out = design_diversity.main([str(run), "--epochs", "2", "--out", str(tmp_path / "d.csv")])
    first, last = common.read_rows(out)
    assert (first["window"], first["epochs"], first["designs"]) == ("first 2 epochs", "0-1", "4")
    assert float(first["distance"]) == 0.0 and first["distinct"] == "1"
    assert float(first["return"]) == pytest.approx(1.0) and float(first["volume"]) == pytest.approx(12.0)
    assert last["epochs"] == "2-3" and last["distinct"] == "2"
    assert float(last["distance"]) == pytest.approx(4 / 6 * 3 / 216)
    assert float(last["return"]) == pytest.approx(3.0) and float(last["volume"]) == pytest.approx(13.5)

    with pytest.raises(ValueError, match="exists"):  # nothing written is overwritten
        design_diversity.main([str(run), "--epochs", "2", "--out", str(out)])
    with pytest.raises(ValueError, match="no such run directory"):
        design_diversity.main([str(tmp_path / "nothing"), "--out", str(tmp_path / "e.csv")])
    with pytest.raises(ValueError, match=r"4 epochs of design records.*--epochs 3 needs at least 6"):
        design_diversity.main([str(run), "--epochs", "3", "--out", str(tmp_path / "e.csv")])
    assert not (tmp_path / "e.csv").exists()


def test_locomotion_metrics_figure_from_records(record_runs, tmp_path):
    from experiments import locomotion

    out = locomotion.main([*map(str, record_runs), "--out", str(tmp_path)])
    assert out["png"].is_file() and out["pdf"].is_file()
    _, cols = common.read_csv(out["csv"])
    trials = [common.load_trial(r) for r in record_runs]
    for key, _ in locomotion.PANELS:
        per_trial = np.array([t.reward if key == "reward" else t.metrics[key] for t in trials])
        mean = per_trial.mean(0)
        np.testing.assert_allclose(cols[f"{key}_raw_mean"], mean, rtol=1e-5)
        np.testing.assert_allclose(cols[f"{key}_mean"], common.moving_average(mean), rtol=1e-5)
        assert np.all(cols[f"{key}_upper"] >= cols[f"{key}_mean"] - 1e-9)


# ---------------------------------------------------------------------------------------------------- tiny runs
def _tiny_sweep(root: Path, task: str, seeds=(0, 1), epochs: int = 2) -> list[Path]:
    """Real runs of the training app at toy sizes (locomotion: 0.1 s of simulated time)."""
    from freeform.config import AgentConfig, EnvConfig, TaskConfig, TrainConfig, TrainerConfig
    from freeform.sim import SimConfig
    from freeform.train import train

    runs = []
    for seed in seeds:
        cfg = TrainConfig(
            name=f"tiny_{task}", seed=seed,
            task=TaskConfig(name=task, materials=4 if task == "locomotion" else 2,
                            options={"arch": "cpu"} if task == "locomotion" else {}),
            env=EnvConfig(num_envs=6, resolution=6, steps=4),
            agent=AgentConfig(hidden=16, num_sgd_iter=2, sgd_minibatch_size=12),
            sim=SimConfig(burn_in=0.05, duration=0.05),
            trainer=TrainerConfig(epochs=epochs, device="cpu", progress=False, print_every=0, checkpoint_every=1),
        )
        runs.append(train(cfg, root / f"seed={seed}").run_dir)
    return runs


@pytest.fixture(scope="module")
def volume_runs(tmp_path_factory) -> list[Path]:
    return _tiny_sweep(tmp_path_factory.mktemp("volume"), "volume")


@pytest.fixture(scope="module")
def locomotion_runs(tmp_path_factory) -> list[Path]:
    return _tiny_sweep(tmp_path_factory.mktemp("locomotion"), "locomotion")


def test_provenance_of_real_runs_names_versions_device_and_commit(volume_runs):
    import torch

    prov = common.provenance(volume_runs)
    assert prov["torch"] == torch.__version__ and prov["device"].startswith("cpu") and prov["freeform"] != "unknown"
    assert prov["taichi"] != "unknown" and prov["git_commit"] != "unknown"


def test_untrained_critic_is_the_seeded_initial_network(volume_runs):
    """The epoch-0 checkpoint and a network rebuilt from config + seed (the fallback) are the same network."""
    import torch

    from experiments import critic
    from freeform.agents import VoxelActorCritic
    from freeform.train import seed_everything

    net = critic.untrained_critic(volume_runs[1], torch.device("cpu"))
    seed_everything(1)
    rebuilt = VoxelActorCritic(resolution=6, materials=2, hidden=16)
    for (k, a), b in zip(net.state_dict().items(), rebuilt.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, msg=k)
    trained = critic.load_critic(volume_runs[1] / "checkpoints" / "last.pt", torch.device("cpu"))
    assert not torch.equal(trained.critic_out.weight, net.critic_out.weight)


def test_critic_figure_in_and_out_of_domain(volume_runs, tmp_path):
    import torch

    from experiments import critic
    from freeform.records import read_record, record_path

    out = critic.main([str(volume_runs[0].parent), "--out", str(tmp_path), "--device", "cpu"])
    assert out["png"].is_file() and out["pdf"].is_file()
    _, cols = common.read_csv(out["csv"])
    np.testing.assert_array_equal(cols["epoch"], [0, 1])
    # Independent recomputation for epoch 1: critic 0 on trial 0's robots (in) and on trial 1's (out).
    net = critic.load_critic(volume_runs[0] / "checkpoints" / "last.pt", torch.device("cpu"))
    recs = [read_record(record_path(r, 1)) for r in volume_runs]
    with torch.no_grad():
        v_in = net(torch.as_tensor(recs[0].final_grids))[2].numpy()
        v_out = net(torch.as_tensor(recs[1].final_grids))[2].numpy()
    in_err0 = np.abs(v_in - recs[0].rewards).mean()
    out_err0 = np.abs(v_out - recs[1].rewards).mean()
    n = 2  # critics; CSV holds the mean over critics: recompute critic 1 the same way
    net1 = critic.load_critic(volume_runs[1] / "checkpoints" / "last.pt", torch.device("cpu"))
    with torch.no_grad():
        in_err1 = np.abs(net1(torch.as_tensor(recs[1].final_grids))[2].numpy() - recs[1].rewards).mean()
        out_err1 = np.abs(net1(torch.as_tensor(recs[0].final_grids))[2].numpy() - recs[0].rewards).mean()
    assert cols["in_err_trained_raw_mean"][1] == pytest.approx((in_err0 + in_err1) / n, rel=1e-4)
    assert cols["out_err_trained_raw_mean"][1] == pytest.approx((out_err0 + out_err1) / n, rel=1e-4)
    assert cols["in_reward_raw_mean"][1] == pytest.approx((recs[0].rewards.mean() + recs[1].rewards.mean()) / 2,
                                                          rel=1e-5)


def _bundle_cells(a: np.ndarray, rho: int) -> int:
    """Spec design.md: cells of a 2-voxel bundle on each axis = {ceil(ρ f) − 1, ceil(ρ f)} ∩ [0, ρ − 1]."""
    f = 0.5 + np.clip(a[:3], -2, 2) / 4
    c = np.ceil(rho * f)
    return int(np.prod([len({c[d] - 1, c[d]} & set(range(rho))) for d in range(3)]))


def test_robustness_replays_volume_runs_exactly(volume_runs, tmp_path):
    from experiments import robustness
    from freeform.records import read_record, record_path

    out = robustness.main([*map(str, volume_runs), "--out", str(tmp_path)])
    assert out["png"].is_file() and out["pdf"].is_file()
    _, cols = common.read_csv(out["csv"])
    np.testing.assert_array_equal(cols["t"], [1, 2, 3, 4])
    recs = [read_record(record_path(r, 1)) for r in volume_runs]  # the last recorded epoch
    # t = T: the replayed designs are the recorded ones, so the volume reward is the recorded reward.
    assert cols["mean"][-1] == pytest.approx(np.concatenate([r.rewards for r in recs]).mean(), rel=1e-5)
    # t = 1: one bundle on an empty grid (material 1 if w_1 > w_0, else nothing): its cells by the spec's rule.
    first = [(_bundle_cells(a[0], 6) if np.argmax(0.5 + np.clip(a[0, 3:], -2, 2) / 4) == 1 else 0)
             for r in recs for a in r.actions]
    assert cols["mean"][0] == pytest.approx(np.mean(first), rel=1e-5)
    assert cols["n"][0] == 12


def test_robustness_of_locomotion_runs_resimulates_the_recorded_designs(locomotion_runs, tmp_path):
    from experiments import robustness
    from freeform.records import read_record, record_path

    out = robustness.main([str(locomotion_runs[0]), "--out", str(tmp_path), "--steps", "1", "4"])
    _, cols = common.read_csv(out["csv"])
    np.testing.assert_array_equal(cols["t"], [1, 4])
    rec = read_record(record_path(locomotion_runs[0], 1))
    # Same bodies, same protocol, same engine: the final designs earn their recorded rewards again.
    assert cols["mean"][-1] == pytest.approx(rec.rewards.mean(), rel=1e-4, abs=1e-5)
    with pytest.raises(ValueError, match="--steps"):
        robustness.main([str(locomotion_runs[0]), "--out", str(tmp_path), "--steps", "9"])


def test_hparams_table_from_the_configs_used(volume_runs, locomotion_runs, tmp_path):
    from experiments import hparams

    out = hparams.main([str(volume_runs[0].parent), str(locomotion_runs[0].parent), "--out", str(tmp_path)])
    prov, cols = common.read_csv(out["csv"])
    rows = list(cols["hyperparameter"])
    vol, loco = cols["tiny_volume"], cols["tiny_locomotion"]
    assert vol[rows.index("PPO Batch Size")] == "24"  # N·T = 6·4
    assert str(loco[rows.index("Actor MLP Size")]) == "(16, 16)"
    assert loco[rows.index("Burn-in / evaluation (s)")] == "0.05 / 0.05"
    assert vol[rows.index("Seeds")] == "0, 1"
    assert "PPO GAE" in out["md"].read_text() and r"\begin{tabular}" in out["tex"].read_text()


def test_rescore_reproduces_the_recorded_rewards_and_applies_the_overrides(locomotion_runs, tmp_path):
    from experiments import rescore
    from freeform.records import read_record, record_path

    run = str(locomotion_runs[0])
    out = rescore.main([run, "--out", str(tmp_path), "--set", "sim.burn_in=0.05"])  # the run's own protocol
    _, cols = common.read_csv(out["csv"])
    np.testing.assert_array_equal(cols["epoch"], [0, 1])
    for i, epoch in enumerate((0, 1)):
        recorded = read_record(record_path(locomotion_runs[0], epoch)).rewards.mean()
        assert cols["recorded"][i] == pytest.approx(recorded, rel=1e-5)  # the CSV keeps 6 digits
        # the same designs, protocol and engine earn their recorded rewards again, and so does the identity override
        assert cols["as_trained"][i] == pytest.approx(recorded, rel=1e-4, abs=1e-5)
        assert cols["rescored"][i] == cols["as_trained"][i]
    out = rescore.main([run, "--out", str(tmp_path), "--set", "sim.burn_in=0.3", "--epochs", "last"])
    _, cols = common.read_csv(out["csv"])
    assert len(cols["epoch"]) == 1 and cols["rescored"][0] != pytest.approx(cols["as_trained"][0], rel=1e-3)
    with pytest.raises(ValueError, match="--epochs"):
        rescore.main([run, "--out", str(tmp_path), "--set", "sim.burn_in=0.3", "--epochs", "7"])
    with pytest.raises(ValueError, match="--set"):
        rescore.main([run, "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="sim.burn_in"):
        rescore.main([run, "--out", str(tmp_path), "--set", "sim.burn_in=-1"])


def test_policy_eval_designs_with_the_checkpoint_and_scores_under_the_given_protocol(locomotion_runs, tmp_path):
    """The same policy and noise design the same bodies whatever the protocol (metrics equal); the run's own
    protocol given as an override changes nothing; another burn-in changes the rewards and is recorded."""
    from experiments import policy_eval

    run, common_args = str(locomotion_runs[0]), ["--episodes", "6", "--out", str(tmp_path)]
    prov_own, own = common.read_csv(policy_eval.main([run, *common_args])["csv"])
    _, same = common.read_csv(policy_eval.main([run, *common_args, "--set", "sim.burn_in=0.05"])["csv"])
    prov_other, other = common.read_csv(policy_eval.main([run, *common_args, "--set", "sim.burn_in=0.3"])["csv"])
    np.testing.assert_array_equal(own["epoch"], [0, 2])
    for key in ("reward_mean", "volume_mean", "passive_ratio_mean"):
        np.testing.assert_array_equal(same[key], own[key])
    np.testing.assert_array_equal(other["volume_mean"], own["volume_mean"])
    assert not np.allclose(other["reward_mean"], own["reward_mean"], rtol=1e-3)
    assert "overrides" not in prov_own and prov_other["overrides"] == "sim.burn_in=0.3"
    with pytest.raises(ValueError, match="sim.burn_in"):
        policy_eval.main([run, *common_args, "--set", "sim.burn_in=-1"])


def test_a_fractions_band_covers_the_true_fraction_99_times_in_100():
    """ratio_band: over 2,000 replicate sets of 32 bodies whose figures are 0.6 of their references times noise,
    the 99 % band holds the true fraction (0.6) in 97.5-99.7 % of them (the delta method, a little under 99 % at
    n = 32); a figure exactly proportional to its reference has no band."""
    from freeform.tables import ratio_band

    rng = np.random.default_rng(0)
    held = 0
    for _ in range(2000):
        reference = rng.lognormal(0.8, 0.5, 32)
        values = 0.6 * reference * (1 + rng.normal(0, 0.3, 32)) + rng.normal(0, 0.2, 32)
        ratio, half = ratio_band(values, reference)
        held += abs(ratio - 0.6) <= half
    assert 0.975 <= held / 2000 <= 0.997
    assert ratio_band(np.array([1.0, 2.0, 4.0]) * 0.5, np.array([1.0, 2.0, 4.0])) == (0.5, 0.0)
    with pytest.raises(ValueError, match="positive mean reference"):
        ratio_band(np.ones(3), np.zeros(3))
