"""lab.selection: each body the best of several controllers' tables, and the exact best of k."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from experiments.common import read_rows, write_rows
from lab.selection import best_of_k, beyond_best_of_k, main, select, table_name, try_controllers


def test_the_best_of_k_and_its_passing_the_gait_are_the_means_over_every_k_subset() -> None:
    """Truth: enumerate every k-subset of C controllers (itertools.combinations), take each body's best in it, and
    average it, and its passing the body's gait; ties included (two controllers equal on a body)."""
    rng = np.random.default_rng(0)
    values = rng.normal(size=(6, 9))
    values[2, 0] = values[4, 0]
    for k in range(1, 7):
        brute = np.mean([values[list(s)].max(0) for s in itertools.combinations(range(6), k)], axis=0)
        np.testing.assert_allclose(best_of_k(values, k), brute, rtol=1e-12)
    np.testing.assert_allclose(best_of_k(values, 1), values.mean(0))
    gaits = rng.normal(size=9)
    for k in range(1, 7):  # (the chance that a k-subset's best passes the body's gait, over bodies)
        brute = np.mean([values[list(s)].max(0) > gaits for s in itertools.combinations(range(6), k)])
        assert beyond_best_of_k(values, gaits, k) == pytest.approx(brute, rel=1e-12)
    with pytest.raises(ValueError, match=r"k must be in \[1, 6\]"):
        best_of_k(values, 7)


def table(path: Path, moves: list[float], gaits: list[float], per_body: list[float] | None = None,
          headings: str | None = "any") -> Path:
    """A held-out table as the results keep one (``<name>_bodies.csv`` beside ``<name>_run.json``, which records
    the task unless ``headings`` is None)."""
    rows = [{"set": "s", "body": i, "open_loop": g, "controller": m - 0.1, "mean_command": m, "hand_set_wave": 1.0,
             **({"per_body_mean_command": per_body[i]} if per_body else {})}
            for i, (m, g) in enumerate(zip(moves, gaits, strict=True))]
    if headings is not None:
        path.with_name(path.name.replace("bodies.csv", "run.json")).write_text(
            json.dumps({"control": {"headings": headings}}))
    return write_rows(path, rows)


def pooled_table(tmp_path: Path, headings: str, file: str = "c.pt", moves: tuple[float, float] = (1.2, 1.2),
                 files: tuple[str, str] | None = None) -> Path:
    """Two one-body sets (bodies of ``x.npy`` and ``y.npy``) evaluated with the controller ``file`` (each set its
    own of ``files`` where given), pooled by ``lab.heldout.pool``, their run.json recording the task."""
    from lab.heldout import pool

    sets, where = [], tmp_path / f"pooled_{headings}_{Path(file).stem}"
    for name, gait, move, each in zip("xy", (0.3, 0.4), moves, files or (file, file), strict=True):
        folder = where.with_name(f"{where.name}_{name}")
        write_rows(folder / "bodies.csv", [{"body": 0, "open_loop": gait, "controller": 1.0, "mean_command": move,
                                            "hand_set_wave": 1.0}])
        (folder / "run.json").write_text(json.dumps({"controller": each, "kind": "attention", "seed": 0,
                                                     "control": {"headings": headings}, "bodies": f"{name}.npy"}))
        sets.append(folder)
    pool(sets, where)
    return where


def test_each_body_gets_its_best_controller_and_the_curve_runs_from_their_mean_to_that(tmp_path: Path) -> None:
    """Three controllers on four bodies: body by body the chosen one is the table of the largest mean command; the
    curve's k = 1 is the controllers' mean and k = 3 the chosen mean; the fractions are sums against per-body
    control, means against the hand-set wave, counts beyond the gait; shares of choices sum to 1."""
    gaits, per = [0.5, 0.2, 0.9, 0.1], [2.0, 2.0, 2.0, 2.0]
    moves = np.array([[1.0, 0.1, 0.8, 2.0], [0.4, 0.3, 1.2, 1.0], [0.9, 0.25, 0.7, 0.0]])
    tables = [table(tmp_path / f"{n}_bodies.csv", list(m), gaits, per) for n, m in zip("abc", moves, strict=True)]
    curve = select(tables, tmp_path / "out")
    rows = read_rows(tmp_path / "out" / "bodies.csv")
    assert [r["chosen"] for r in rows] == ["a", "b", "b", "a"]
    np.testing.assert_allclose([float(r["mean_command"]) for r in rows], moves.max(0))
    assert [float(r["mean_command_c"]) for r in rows] == list(moves[2])
    assert [c["k"] for c in curve] == [1, 2, 3]
    assert curve[0]["mean"] == pytest.approx(moves.mean())
    best = moves.max(0)
    assert curve[2] == pytest.approx({"k": 3, "mean": best.mean(), "beyond_own_gait": 1.0,
                                      "fraction_of_per_body": best.sum() / 8.0, "over_hand_set_wave": best.mean()})
    assert curve[0]["beyond_own_gait"] == pytest.approx(np.mean(moves > np.array(gaits)))
    summary = {r["what"]: float(r["mean"]) for r in read_rows(tmp_path / "out" / "summary.csv")}
    assert summary["chosen: a"] == 0.5 and summary["chosen: b"] == 0.5 and summary["chosen: c"] == 0.0
    assert json.loads((tmp_path / "out" / "run.json").read_text())["names"] == ["a", "b", "c"]
    assert [r["controller_file"] for r in rows] == ["", "", "", ""]  # (these tables' run.json names no file)
    c = pooled_table(tmp_path, "any", "c.pt", files=("c_x.pt", "c_y.pt"))
    d = pooled_table(tmp_path, "any", "d.pt", (0.0, 2.0))
    select([c, d], tmp_path / "f")
    assert [r["controller_file"] for r in read_rows(tmp_path / "f" / "bodies.csv")] == ["c_x.pt", "d.pt"]
    alone = tmp_path / "alone"  # (one set's table: its run.json's controller)
    write_rows(alone / "bodies.csv", [{"set": "s", "body": 0, "open_loop": 0.3, "mean_command": 0.1},
                                      {"set": "s", "body": 1, "open_loop": 0.4, "mean_command": 9.0}])
    (alone / "run.json").write_text(json.dumps({"controller": "e.pt", "control": {"headings": "any"}}))
    twin = table(tmp_path / "twin_bodies.csv", [0.2, 0.0], [0.3, 0.4])
    select([twin, alone], tmp_path / "g")
    assert [r["controller_file"] for r in read_rows(tmp_path / "g" / "bodies.csv")] == ["", "e.pt"]
    assert [table_name(Path(p)) for p in ("runs/try_g4", "runs/try_g4/bodies.csv", "h/s64_g4_bodies.csv")] == \
        ["try_g4", "try_g4", "s64_g4"]


def test_tables_of_other_bodies_or_too_few_are_refused_naming_the_problem(tmp_path: Path, capsys) -> None:
    """A table whose body walks another gait (another body, or other episode settings), a single table, names that
    do not match the tables, a table along random headings (its trial one draw) and a table without the mean
    command are refused; nothing is written."""
    a = table(tmp_path / "a_bodies.csv", [1.0, 1.0], [0.5, 0.2])
    other = table(tmp_path / "other_bodies.csv", [1.0, 1.0], [0.5, 0.9])
    with pytest.raises(ValueError, match=r"body \('s', '1'\) of .*a_bodies.csv is not body"):
        select([a, other], tmp_path / "out")
    with pytest.raises(ValueError, match="at least two controllers' tables"):
        select([a], tmp_path / "out")
    with pytest.raises(ValueError, match="one distinct name a table"):
        select([a, a], tmp_path / "out", ["x", "x"])
    steering = table(tmp_path / "steer_bodies.csv", [1.0, 1.0], [0.5, 0.2], headings="random")
    with pytest.raises(ValueError, match="steer_bodies.csv: evaluated along random headings"):
        select([a, steering], tmp_path / "out")
    pooled = pooled_table(tmp_path, "random")  # (as lab.heldout --pool records the task)
    with pytest.raises(ValueError, match="pooled_random_c: evaluated along random headings"):
        select([pooled, pooled_table(tmp_path, "any")], tmp_path / "out")
    gap = table(tmp_path / "gap_bodies.csv", [1.0, float("nan")], [0.5, 0.2])
    with pytest.raises(ValueError, match="gap_bodies.csv: body 1 has no mean command"):
        select([a, gap], tmp_path / "out")
    write_rows(tmp_path / "bare.csv", [{"body": 0, "open_loop": 0.5}, {"body": 1, "open_loop": 0.2}])
    with pytest.raises(SystemExit), pytest.warns(UserWarning, match="record no task"):
        main([str(a), str(tmp_path / "bare.csv"), "--out", str(tmp_path / "out")])
    assert "no ['mean_command'] column" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_mean_command_episode_repeats_to_the_bit_so_a_trial_is_the_figure(tmp_path: Path) -> None:
    """The premise of selecting on a table: a controller's mean command walks each body the same in every episode
    (the simulator and the mean are deterministic; the evaluation's noise reaches the stochastic groups alone), so
    two episodes' mean equals one episode's, body by body, while the stochastic column moves."""
    from dataclasses import replace

    import torch

    from freeform.agents.controller_file import save_controller
    from freeform.agents.networks.controller_heads import HandSetWave
    from freeform.agents.networks.controllers import ContextConvController
    from freeform.envs.control import ControlEnv
    from freeform.sim import SimConfig
    from lab.control import main as evaluate
    from tests.test_control_evaluate import SHORT, tiny_bodies

    control = replace(SHORT, stroke_periods=1)
    env = ControlEnv(tiny_bodies(), control=control)
    torch.manual_seed(0)  # (a wave head: its mean command moves the bodies)
    net = ContextConvController.for_env(env, hidden=4, log_std=-1.0, head="wave", wave=HandSetWave(1.5, 1.2))
    save_controller(tmp_path / "controller.pt", net, control, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    for n in ("1", "2"):
        evaluate(["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "any",
                  "--eval-episodes", n, "--out", str(tmp_path / n)])
    one, two = (read_rows(tmp_path / n / "bodies.csv") for n in ("1", "2"))
    assert any(abs(float(r["mean_command"])) > 1e-4 for r in one)  # (they move: 0 = 0 would pass)
    assert [r["mean_command"] for r in one] == [r["mean_command"] for r in two]
    assert [r["controller"] for r in one] != [r["controller"] for r in two]


def test_a_partial_reference_or_an_unrecorded_task_is_warned_about_and_a_tie_goes_to_the_first(tmp_path: Path) -> None:
    """A per-body column on part of the bodies leaves the fraction of per-body control out, warned; a table that
    records no task is warned about; one whose per-body column is whole gives it wherever it stands; on a tie the
    earlier table is chosen; a body whose best only equals its gait is not beyond it; tables of two hosts are
    warned about once."""
    a = table(tmp_path / "a_bodies.csv", [1.0, 0.2], [0.5, 0.2], per_body=[2.0, float("nan")])
    b = table(tmp_path / "b_bodies.csv", [1.0, 0.1], [0.5, 0.2])
    with pytest.warns(UserWarning, match="per_body_mean_command is there for part of the bodies only"):
        curve = select([a, b], tmp_path / "out")
    assert "fraction_of_per_body" not in curve[0]
    assert [r["chosen"] for r in read_rows(tmp_path / "out" / "bodies.csv")] == ["a", "a"]
    assert curve[-1]["beyond_own_gait"] == 0.5  # (body 1's best, 0.2, equals its gait)
    whole = table(tmp_path / "w_bodies.csv", [0.5, 0.0], [0.5, 0.2], per_body=[2.0, 2.0])
    curve = select([b, whole], tmp_path / "out2")
    assert curve[-1]["fraction_of_per_body"] == pytest.approx(1.1 / 4.0)
    bare = table(tmp_path / "n_bodies.csv", [1.0, 0.1], [0.5, 0.2], headings=None)
    with pytest.warns(UserWarning, match="1 of the tables .* record no task"):
        select([b, bare], tmp_path / "out3")
    drifted = table(tmp_path / "h_bodies.csv", [1.0, 0.1], [0.5001, 0.2001])  # (another host's floating point)
    with pytest.warns(UserWarning, match="1 table-and-set pairs of these tables were measured on two hosts") as said:
        select([b, drifted], tmp_path / "out4")
    assert sum("two hosts" in str(w.message) for w in said) == 1


def wave_controllers(tmp_path: Path, seeds: tuple[int, ...]) -> list[Path]:
    """Tiny wave-head controllers (their mean commands move the bodies), one file each, of one episode."""
    from dataclasses import replace

    import torch

    from freeform.agents.controller_file import save_controller
    from freeform.agents.networks.controller_heads import HandSetWave
    from freeform.agents.networks.controllers import ContextConvController
    from freeform.envs.control import ControlEnv
    from freeform.sim import SimConfig
    from tests.test_control_evaluate import SHORT, tiny_bodies

    control = replace(SHORT, stroke_periods=1)
    env = ControlEnv(tiny_bodies(), control=control)
    files = []
    for seed in seeds:
        torch.manual_seed(seed)
        net = ContextConvController.for_env(env, hidden=4, log_std=-1.0, head="wave", wave=HandSetWave(1.5, 1.2))
        with torch.no_grad():  # (the learnt parts large enough that the two walk the bodies apart)
            for layer in (net.actor, net.wave_k):
                layer.weight.mul_(20.0)
        files.append(save_controller(tmp_path / f"c{seed}" / "controller.pt", net, control, SimConfig()))
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    return files


def test_trying_controllers_in_one_env_gives_each_the_figure_its_own_evaluation_gives(tmp_path: Path) -> None:
    """Truth: each controller's own zero-shot evaluation (lab.control --evaluate, one episode a body, run
    alone). Tried together, each controller's mean command, the hand-set wave and the bodies' own gaits equal its
    table's, body by body; the choice is the larger; the moves after each decision end at the episode's figure; a
    choice by the first decision is scored by the whole episode, and its best of k follows that trial."""
    from lab.control import main as evaluate

    files = wave_controllers(tmp_path, (0, 2))
    bodies = tmp_path / "bodies.npy"
    tables = []
    for f in files:
        evaluate(["--evaluate", str(f), "--bodies", str(bodies), "--headings", "any", "--eval-episodes", "1",
                  "--out", str(f.parent / "table")])
        tables.append(read_rows(f.parent / "table" / "bodies.csv"))
    main(["--try", *map(str, files), "--bodies", str(bodies), "--headings", "any", "--out", str(tmp_path / "tried"),
          "--names", "a", "b"])
    rows = read_rows(tmp_path / "tried" / "bodies.csv")
    values = np.array([[float(r[f"mean_command_{n}"]) for r in rows] for n in "ab"])
    np.testing.assert_array_equal(values, [[float(r["mean_command"]) for r in t] for t in tables])
    assert not np.allclose(values[0], values[1])  # (two controllers that walk apart: a choice to make)
    for column in ("hand_set_wave", "open_loop"):
        np.testing.assert_allclose([float(r[column]) for r in rows], [float(r[column]) for r in tables[0]],
                                   rtol=1e-12)
    assert [r["chosen"] for r in rows] == ["ab"[i] for i in values.argmax(0)]
    assert [r["controller_file"] for r in rows] == [str(files[i]) for i in values.argmax(0)]
    moves = np.load(tmp_path / "tried" / "moves.npy")
    assert moves.shape == (2, 4, len(rows))
    np.testing.assert_allclose(moves[:, -1], values, rtol=1e-12)
    main(["--try", *map(str, files), "--bodies", str(bodies), "--headings", "any", "--trial-decisions", "1",
          "--out", str(tmp_path / "first")])
    first = read_rows(tmp_path / "first" / "bodies.csv")
    picked = moves[:, 0].argmax(0)
    assert (picked != values.argmax(0)).any()  # (the first decision chooses otherwise than the whole episode)
    assert [r["chosen"] for r in first] == [("c0", "c2")[i] for i in picked]
    np.testing.assert_allclose([float(r["mean_command"]) for r in first], values[picked, np.arange(len(rows))])
    np.testing.assert_allclose([float(r["trial_c2"]) for r in first], moves[1, 0])
    curve = read_rows(tmp_path / "first" / "best_of_k.csv")
    assert float(curve[-1]["mean"]) == pytest.approx(values[picked, np.arange(len(rows))].mean())


def test_the_best_of_k_by_a_trial_is_the_mean_over_every_k_subset_of_the_trials_choice() -> None:
    """Truth: enumerate every k-subset; in each, the controller with the best trial (the earlier on a tie) is
    chosen and scored by its whole figure; the expectation and its passing the gait are the means over subsets."""
    rng = np.random.default_rng(1)
    values, trial = rng.normal(size=(5, 7)), rng.normal(size=(5, 7))
    trial[1, 0] = trial[3, 0]
    gaits = rng.normal(size=7)
    for k in range(1, 6):
        picks = [np.array(s)[trial[list(s)].argmax(0)] for s in itertools.combinations(range(5), k)]
        scored = np.array([values[p, np.arange(7)] for p in picks])
        np.testing.assert_allclose(best_of_k(values, k, trial), scored.mean(0), rtol=1e-12)
        assert beyond_best_of_k(values, gaits, k, trial) == pytest.approx(np.mean(scored > gaits), rel=1e-12)
    with pytest.raises(ValueError, match="the trial's figures"):
        best_of_k(values, 2, trial[:, :3])


def test_trying_refuses_what_is_no_trial_before_playing(tmp_path: Path, capsys) -> None:
    """One controller, a trial longer than the episode, random headings, controllers of two episodes or simulators
    (the physics field named; another schedule plays: it runs the same physics), a reference
    of other bodies or without per-body control, and tables with --try are refused naming the problem; nothing is
    written (all before the play but the reference of other bodies, whose gaits are compared with the played ones).
    Fixed headings, the other task with no draw, play."""
    from dataclasses import replace

    from freeform.agents.controller_file import read_controller, save_controller

    files = wave_controllers(tmp_path, (0,)) * 2
    bodies, out = tmp_path / "bodies.npy", tmp_path / "out"
    with pytest.raises(ValueError, match="at least two controllers"):
        try_controllers(files[:1], bodies, out)
    with pytest.raises(ValueError, match=r"--trial-decisions must be in \[1, 4\]"):
        try_controllers(files, bodies, out, trial=5, names=["a", "b"])
    with pytest.raises(ValueError, match="along random headings"):
        try_controllers(files, bodies, out, names=["a", "b"], headings="random")
    saved = read_controller(files[0])
    longer = save_controller(tmp_path / "longer.pt", saved.controller, replace(saved.control, duration=0.1),
                             saved.sim)
    with pytest.raises(ValueError, match="plays another episode .* control.duration"):
        try_controllers([files[0], longer], bodies, out)
    heavier = save_controller(tmp_path / "heavier.pt", saved.controller, saved.control,
                              replace(saved.sim, gravity=-1.0, schedule="robots"))
    with pytest.raises(ValueError, match=r"heavier.pt plays another episode .* sim\.gravity: -1\.0 in .*heavier\.pt, -9\.81 in .*c0/controller.pt: try"):
        try_controllers([files[0], heavier], bodies, out)  # (the physics named, the schedule not: how it runs)
    few = table(tmp_path / "few_bodies.csv", [1.0], [0.5], per_body=[2.0])
    with pytest.raises(ValueError, match="1 bodies, not the 3 tried"):
        try_controllers(files, bodies, out, names=["a", "b"], reference=few)
    bare = table(tmp_path / "bare_bodies.csv", [1.0] * 3, [0.5] * 3)
    with pytest.raises(ValueError, match="no per_body_mean_command for every body"):
        try_controllers(files, bodies, out, names=["a", "b"], reference=bare)
    other = table(tmp_path / "o_bodies.csv", [1.0] * 3, [0.5] * 3, per_body=[2.0] * 3)
    with pytest.raises(ValueError, match="is not body"):
        try_controllers(files, bodies, out, names=["a", "b"], reference=other)
    with pytest.raises(SystemExit):
        main([str(few), "--try", *map(str, files), "--bodies", str(bodies), "--out", str(out)])
    assert "not both" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(few), str(bare), "--bodies", str(bodies), "--out", str(out)])
    assert "go with --try; got --bodies" in capsys.readouterr().err
    fixed = tmp_path / "fixed"
    try_controllers(files, bodies, fixed, names=["a", "b"], headings="fixed")  # (the other fixed task: it plays)
    scheduled = save_controller(tmp_path / "scheduled.pt", saved.controller, saved.control,
                                replace(saved.sim, schedule="robots" if saved.sim.schedule != "robots" else "auto"))
    try_controllers([files[0], scheduled], bodies, tmp_path / "scheduled", names=["a", "b"])  # (the same physics)
    assert json.loads((fixed / "run.json").read_text())["control"]["headings"] == "fixed"
    assert not out.exists()
