"""Hard EM over experts (freeform.agents.distill.experts) and the lab's tools on a teacher run (lab.experts,
lab.reference). With points for bodies, centres for experts, the negative squared distance for a trial and the mean
of the points won for a refit, hard EM must be Lloyd's k-means — checked against scipy's ``kmeans2`` from the same
start."""

import numpy as np
import pytest
from scipy.cluster.vq import kmeans2

from freeform.agents.distill.experts import assign, hard_em


def _clouds(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 5.0], [5.0, 5.0]])
    return np.concatenate([c + rng.normal(0, 0.9, (30, 2)) for c in centres])


def _lloyd(points: np.ndarray):
    calls = []

    def trial(experts):  # [K, M]: the bodies' moves under each expert
        return -((points[None] - np.stack(experts)[:, None]) ** 2).sum(-1)

    def refit(k, expert, bodies):
        calls.append(k)
        return points[bodies].mean(0)

    return trial, refit, calls


def test_hard_em_is_lloyds_kmeans_from_the_same_start():
    points = _clouds()
    start = points[[0, 1, 2, 40]]  # (three in the first cloud: the assignment must move many bodies)
    trial, refit, _ = _lloyd(points)
    em = hard_em(list(start), trial, refit, rounds=50)
    centres, labels = kmeans2(points, start.copy(), iter=50, minit="matrix", missing="warn")
    assert em.fixed_point and len(em.history) > 3  # (it reassigned bodies several times before settling)
    np.testing.assert_array_equal(em.assignment, labels)
    np.testing.assert_allclose(np.stack(em.experts), centres, atol=1e-12)
    firsts = [r.assignment for r in em.history]
    assert not np.array_equal(firsts[0], firsts[-1])


def test_a_fixed_point_stays_one():
    points = _clouds(1)
    centres, labels = kmeans2(points, points[[0, 30, 60, 90]].copy(), iter=100, minit="matrix", missing="warn")
    trial, refit, calls = _lloyd(points)
    em = hard_em(list(centres), trial, refit, rounds=10)
    assert em.fixed_point and len(em.history) == 2  # (one refit, and the assignment it gives is the one it had)
    np.testing.assert_array_equal(em.assignment, labels)
    np.testing.assert_array_equal(em.history[0].assignment, em.history[1].assignment)
    np.testing.assert_allclose(np.stack(em.experts), centres, atol=1e-12)
    assert sorted(calls) == [0, 1, 2, 3]  # (every expert refit once, from its own bodies)


def test_a_fixed_expert_keeps_its_bodies_and_is_never_refit():
    points = _clouds(2)
    trial, refit, calls = _lloyd(points)
    wave = np.array([5.0, 5.0])  # (the hand-set wave: an expert nobody trains)
    em = hard_em([points[0], points[1], wave], trial, refit, rounds=20, fixed=[False, False, True])
    assert 2 not in calls and np.array_equal(em.experts[2], wave)
    assert (em.assignment == 2).sum() >= 25  # (the cloud at (5, 5) is the wave's)


def test_an_expert_that_wins_nothing_stays_as_it_is():
    points = _clouds(3)
    trial, refit, calls = _lloyd(points)
    far = np.array([100.0, 100.0])
    em = hard_em([points.mean(0), far], trial, refit, rounds=5)
    assert em.fixed_point and 1 not in calls and np.array_equal(em.experts[1], far)
    assert (em.assignment == 0).all()


def test_assign_ties_go_to_the_earlier_expert_and_refuses_nan():
    np.testing.assert_array_equal(assign(np.array([[1.0, 2.0], [1.0, 3.0]])), [0, 1])
    with pytest.raises(ValueError, match="finite"):
        assign(np.array([[1.0, np.nan]]))
    with pytest.raises(ValueError, match="experts, bodies"):
        assign(np.zeros(3))


def test_rounds_zero_is_the_first_assignment_alone():
    points = _clouds()
    trial, refit, calls = _lloyd(points)
    em = hard_em([points[0], points[100]], trial, refit, rounds=0)
    assert not em.fixed_point and calls == [] and len(em.history) == 1


@pytest.fixture(scope="module")
def three_bodies(tmp_path_factory):
    """A teacher run of three tiny bodies, two epochs, every epoch saved (the lab's EM and reference read it)."""
    from test_control_run import CUBE, ROD
    from test_teacher_pool import WIDE, _teacher_run

    return _teacher_run(tmp_path_factory.mktemp("teachers"), "t", np.stack([ROD, CUBE, WIDE]), "control.teachers=3",
                        "env.num_envs=6", "trainer.epochs=2", "seed=4")


def test_the_lab_driver_distils_each_expert_from_the_teachers_of_the_bodies_it_won(tmp_path, three_bodies):
    """lab.experts end to end at toy sizes: two experts (two teachers of a 3-body run) tried, refit from the
    teachers of the bodies each won (the refit's teacher run holds exactly those), written back as controllers."""
    import csv
    import json

    from freeform.agents.controller_file import read_controller
    from freeform.run.teacher_runs import export_teacher
    from lab.experts import experts_on

    run = three_bodies
    experts = [str(export_teacher(run, i, tmp_path / f"e{i}")) for i in (0, 2)]
    tiny = ("control.controller=context", "control.duration=0.05", "control.burn_in=0.01", "agent.hidden=4",
            "agent.sgd_minibatch_size=8", "sim.precision=f64", "control.head=direct", "control.hidden=4",
            "trainer.threads=1")
    out = tmp_path / "em"
    em = experts_on(run, experts, out, rounds=1, epochs=1, copies=2, overrides=tiny)
    rounds = list(csv.DictReader(open(out / "rounds.csv")))
    first = em.history[0].assignment
    assert len(rounds) == 2 * len(em.history)
    assert [int(r["bodies"]) for r in rounds[:2]] == [int((first == 0).sum()), int((first == 1).sum())]
    for k in range(2):  # (each refit of round 1 was taught by the teachers of the bodies that expert won in round 0)
        taken = out / "round1" / f"teachers{k}" / "pooled.json"
        if (first == k).any():
            assert json.loads(taken.read_text())["sources"][0]["taken"] == np.flatnonzero(first == k).tolist()
        else:
            assert not taken.exists()
        read_controller(out / f"expert{k}" / "controller.pt")
    assert json.loads((out / "run.json").read_text())["refits"] == len(em.history) - 1
    with pytest.raises(FileExistsError):
        experts_on(run, experts, out, rounds=1, epochs=1, overrides=tiny)


def test_the_reference_curve_reads_every_saved_epoch_and_ends_at_each_bodys_own_controller(tmp_path, three_bodies):
    """lab.reference: a per-body bank's convergence curve; its last point is each body's own controller played
    alone on that body."""
    import csv

    import torch

    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint
    from freeform.control.play import play
    from freeform.envs.control import ControlEnv
    from freeform.run.build import read_teacher_run
    from lab.reference import main, saved_epochs

    run = three_bodies
    assert [e for e, _ in saved_epochs(run)] == [0, 1, 2]
    main([str(run), "--out", str(tmp_path / "curve")])
    rows = list(csv.DictReader(open(tmp_path / "curve" / "curve.csv")))
    assert [int(r["epoch"]) for r in rows] == [0, 1, 2] and (tmp_path / "curve" / "curve.png").is_file()
    bodies = list(csv.DictReader(open(tmp_path / "curve" / "bodies.csv")))
    teachers = read_teacher_run(run, str(run))
    bank = bank_from_checkpoint(load_checkpoint(run / "checkpoints" / "last.pt"), str(run))
    control = teachers.config.control.episode()
    for i in range(3):  # (body i alone in an env of its own, driven by teacher i alone)
        env = ControlEnv(teachers.bodies[i:i + 1].to(torch.uint8), sim=teachers.config.sim, control=control, seed=0,
                         box=tuple(bank.member(i).box))
        alone = play(env, [("own", bank.member(i).eval(), False, False)], control.steps, 0).returns[0, 0]
        np.testing.assert_allclose(float(bodies[i]["epoch2"]), alone, rtol=1e-6, atol=1e-9)
    mean = np.mean([float(b["epoch2"]) for b in bodies])
    np.testing.assert_allclose(float(rows[-1]["mean_command"]), mean, rtol=1e-9)
    # lab.fractions: a table of half each body's reference, its bodies 10 on (FIRST 10), is 50 % of it, band 0
    from lab.fractions import main as fractions

    with open(tmp_path / "half.csv", "w") as f:
        f.write("body,mean_command,seconds\n" + "".join(f"{10 + i},{float(b['epoch2']) / 2},1.5\n"
                                                        for i, b in enumerate(bodies)))
    fractions(["--reference", str(tmp_path / "curve"), "--table", f"half={tmp_path / 'half.csv'}:mean_command:10",
               "--out", str(tmp_path / "fractions")])
    row = next(csv.DictReader(open(tmp_path / "fractions" / "fractions.csv")))
    assert row["table"] == "half" and int(row["bodies"]) == 3 and float(row["seconds_a_body"]) == 1.5
    assert float(row["fraction"]) == pytest.approx(0.5, abs=1e-12) and float(row["band99"]) < 1e-12
    lines = (tmp_path / "half.csv").read_text().splitlines()  # (the same table in two parts, A+B)
    (tmp_path / "a.csv").write_text("\n".join(lines[:2]) + "\n")
    (tmp_path / "b.csv").write_text("\n".join([lines[0], *lines[2:]]) + "\n")
    fractions(["--reference", str(tmp_path / "curve"), "--table",
               f"parts={tmp_path / 'a.csv'}+{tmp_path / 'b.csv'}:mean_command:10", "--out", str(tmp_path / "parts")])
    parts = next(csv.DictReader(open(tmp_path / "parts" / "fractions.csv")))
    assert int(parts["bodies"]) == 3 and float(parts["fraction"]) == pytest.approx(0.5, abs=1e-12)
    # COLUMN A|B: each body's best of two candidates' columns (a half and a quarter, the quarter's column the larger
    # on body 11 alone, where it is 1.5 times the reference): 0.5 of the others' reference and 1.5 of body 11's
    with open(tmp_path / "two.csv", "w") as f:
        f.write("body,trial_a,trial_b\n" + "".join(
            f"{10 + i},{float(b['epoch2']) / 2},{float(b['epoch2']) * (1.5 if i == 1 else 0.25)}\n"
            for i, b in enumerate(bodies)))
    fractions(["--reference", str(tmp_path / "curve"), "--table", f"best={tmp_path / 'two.csv'}:trial_a|trial_b:10",
               "--out", str(tmp_path / "best")])
    best = next(csv.DictReader(open(tmp_path / "best" / "fractions.csv")))
    ref2 = np.array([float(b["epoch2"]) for b in bodies])
    assert float(best["fraction"]) == pytest.approx((ref2.sum() + 2 * ref2[1]) / (2 * ref2.sum()), abs=1e-12)
    # a reference trained in parts (A+B): body 0's bank to epoch 2, bodies 1 and 2's stopped at epoch 1; each part
    # is read at its own last epoch, in order (a table of half of those is 50 %)
    for name, rows_of, epochs in (("refA", bodies[:1], (0, 1, 2)), ("refB", bodies[1:], (0, 1))):
        (tmp_path / name).mkdir()
        (tmp_path / name / "bodies.csv").write_text("body," + ",".join(f"epoch{e}" for e in epochs) + "\n" + "".join(
            f"{i}," + ",".join(b[f"epoch{e}"] for e in epochs) + "\n" for i, b in enumerate(rows_of)))
    own = [float(bodies[0]["epoch2"]), float(bodies[1]["epoch1"]), float(bodies[2]["epoch1"])]
    (tmp_path / "own.csv").write_text("body,mean_command\n" + "".join(f"{i},{m / 2}\n" for i, m in enumerate(own)))
    fractions(["--reference", f"{tmp_path / 'refA'}+{tmp_path / 'refB'}", "--table", f"own={tmp_path / 'own.csv'}",
               "--out", str(tmp_path / "inparts")])
    row = next(csv.DictReader(open(tmp_path / "inparts" / "fractions.csv")))
    assert row["reference_epoch"] == "2+1" and float(row["reference"]) == pytest.approx(np.mean(own), abs=1e-12)
    assert float(row["fraction"]) == pytest.approx(0.5, abs=1e-12)
    # --curve: a fit's points body by body (half the reference, then all of it but the second body's half), by seconds
    def fit_curve(name: str, seconds: tuple[float, float], shift, epochs=(0, 4)):
        """A fit's folder whose body i (reference body 10 + i) has moved ``kept`` at ``epochs``, plus shift(e, i)."""
        folder = tmp_path / name
        folder.mkdir()
        with open(folder / "adaptation_bodies.csv", "w") as f:
            f.write("epoch,seconds,body,adapted,kept\n" + "".join(
                f"{e},{s},{10 + i},0,{float(b['epoch2']) * (0.5 if e == 0 or i == 1 else 1.0) + shift(e, i)}\n"
                for e, s in zip(epochs, seconds, strict=True) for i, b in enumerate(bodies)))
        return folder

    fitted = fit_curve("fitted", (1.5, 9.0), lambda e, i: 0.0)
    # (a second curve: the first plus 0.25 a body at epoch 4, the second body 0.5 behind it at epoch 0)
    second = fit_curve("second", (1.0, 7.0), lambda e, i: 0.25 if e else -0.5 * (i == 1))
    fractions(["--reference", str(tmp_path / "curve"), "--curve", f"fit={fitted}:10", "--curve", f"two={second}:10",
               "--out", str(tmp_path / "c")])
    paired = list(csv.DictReader(open(tmp_path / "c" / "paired.csv")))
    assert [(p["curve"], p["against"], int(p["epoch"]), int(p["bodies"]), int(p["ahead"])) for p in paired] == [
        ("two", "fit", 0, 3, 0), ("two", "fit", 4, 3, 3)]
    assert float(paired[1]["difference"]) == pytest.approx(0.25, abs=1e-12) and float(paired[1]["band99"]) < 1e-12
    assert float(paired[0]["difference"]) == pytest.approx(-0.5 / 3, abs=1e-12) and float(paired[0]["band99"]) > 0
    # --pair-by point: a curve measured at epochs 0 and 8 (twice the epochs at half the copies) against the first's
    # 0 and 4, point by point; paired by epoch they share epoch 0 alone
    halves = fit_curve("halves", (1.0, 8.0), lambda e, i: 0.25 if e else 0.0, epochs=(0, 8))
    for by, pairs in (("point", [(0, 0), (8, 4)]), ("epoch", [(0, 0)])):
        fractions(["--reference", str(tmp_path / "curve"), "--curve", f"fit={fitted}:10", "--curve",
                   f"halves={halves}:10", "--pair-by", by, "--out", str(tmp_path / by)])
        rows_by = list(csv.DictReader(open(tmp_path / by / "paired.csv")))
        assert [(int(p["epoch"]), int(p["against_epoch"])) for p in rows_by] == pairs
        assert [float(p["difference"]) for p in rows_by] == pytest.approx([0.0, 0.25][:len(pairs)], abs=1e-12)
    points = [p for p in csv.DictReader(open(tmp_path / "c" / "curve.csv")) if p["curve"] == "fit"]
    ref = np.array([float(b["epoch2"]) for b in bodies])
    assert [(int(p["epoch"]), float(p["seconds_a_body"])) for p in points] == [(0, 1.5), (4, 9.0)]
    assert float(points[0]["fraction"]) == pytest.approx(0.5, abs=1e-12) and float(points[0]["band99"]) < 1e-12
    assert float(points[1]["fraction"]) == pytest.approx(1 - ref[1] / 2 / ref.sum(), abs=1e-12)
    assert float(points[1]["band99"]) > 0 and (tmp_path / "c" / "curve.png").is_file()
    for bad in (f"fit={tmp_path}", f"fit={fitted}", f"fit={fitted}:x"):  # (no fit's curve; FIRST 0 meets no body;
        with pytest.raises(SystemExit):                                     # FIRST not a number: nothing written)
            fractions(["--reference", str(tmp_path / "curve"), "--curve", bad, "--out", str(tmp_path / "d")])
    assert not (tmp_path / "d").exists()
    returns = load_checkpoint(run / "checkpoints" / "last.pt")["return_curve"]
    np.testing.assert_allclose(float(rows[-1]["training_return"]), returns[-1])


def test_a_steering_reference_averages_each_bodys_own_headings_and_a_walkers_takes_one(tmp_path, three_bodies,
                                                                                         capsys):
    """lab.reference of a steering bank (headings random): a body's move is the mean over its episodes 0 … K−1,
    each body i along draws j·M + i (evaluate's and fit's figure episodes), played here body by body, episode by
    episode, in envs of one row; ``--episodes`` above one is refused for a walkers' bank, whose episodes are alike."""
    import csv

    import torch
    from test_control_run import CUBE, ROD
    from test_teacher_pool import WIDE, _teacher_run

    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint
    from freeform.control.play import play
    from freeform.envs.control import ControlEnv
    from freeform.run.build import read_teacher_run
    from lab.reference import main

    run = _teacher_run(tmp_path, "steer", np.stack([ROD, CUBE, WIDE]), "control.teachers=3", "env.num_envs=6",
                       "control.headings=random", "seed=4")
    main([str(run), "--out", str(tmp_path / "curve"), "--episodes", "3"])
    bodies = list(csv.DictReader(open(tmp_path / "curve" / "bodies.csv")))
    teachers = read_teacher_run(run, str(run))
    bank = bank_from_checkpoint(load_checkpoint(run / "checkpoints" / "last.pt"), str(run))
    control = teachers.config.control.episode()
    moves = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            env = ControlEnv(teachers.bodies[i:i + 1].to(torch.uint8), sim=teachers.config.sim, control=control,
                             seed=0, box=tuple(bank.member(i).box), first_env=np.array([3 * j + i]))
            moves[i, j] = play(env, [("own", bank.member(i).eval(), False, False)], control.steps, 0).returns[0, 0]
    assert np.ptp(moves, 1).max() > 1e-5  # (the headings differ, and so does a body's move: another draw shows)
    np.testing.assert_allclose([float(b["epoch1"]) for b in bodies], moves.mean(1), rtol=1e-6, atol=1e-9)
    with pytest.raises(SystemExit):
        main([str(three_bodies), "--out", str(tmp_path / "walkers"), "--episodes", "2"])
    assert "more than one only for steering" in capsys.readouterr().err and not (tmp_path / "walkers").exists()


def test_the_reference_asymptote_recovers_a_saturating_curve_and_refuses_a_straight_line():
    """lab.reference's extrapolation: noisy bodies that follow a_i − b_i·exp(−(t − 30)/60), read from epoch 30 to
    190, give back the mean a, its interval holds it, and the last epoch's share is the curve's own; a noisy straight
    line, which has not bent within its span, gives no asymptote and no interval, nor do three epochs (three points,
    three parameters)."""
    from lab.reference import asymptote

    rng = np.random.default_rng(1)
    t = np.arange(30, 191, 10)
    a, b = rng.uniform(2, 5, 32), rng.uniform(1, 3, 32)
    moves = a[:, None] - b[:, None] * np.exp(-(t[None, :] - 30) / 60) + rng.normal(0, 0.02, (32, len(t)))
    fit = asymptote(t, moves, resamples=50)
    assert fit["asymptote"] == pytest.approx(a.mean(), rel=0.02) and fit["tau_epochs"] == pytest.approx(60, rel=0.1)
    assert fit["low99"] < a.mean() < fit["high99"] < 2 * a.mean() and fit["unbent_resamples"] == 0
    assert fit["reached"] == pytest.approx(moves.mean(0)[-1] / fit["asymptote"], rel=1e-12)
    line = asymptote(t, 1 + 0.02 * t[None, :] + rng.normal(0, 0.02, (32, len(t))), resamples=20)
    assert np.isnan(line["asymptote"]) and np.isnan(line["low99"]) and np.isnan(line["high99"])
    assert line["unbent_resamples"] >= 15
    assert np.isnan(asymptote(t[:3], moves[:, :3], resamples=5)["asymptote"])
