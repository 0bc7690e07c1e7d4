"""Teacher runs trained apart, pooled into one (``freeform.run.teacher_runs``, ``TeacherBank.concatenate``): the pool's
teacher j is the source run's teacher, on the source's body, and a student distils from the pool through the app;
runs that trained another task or other controllers are refused, and nothing in a used folder is overwritten."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_control_run import CUBE, ROD, tiny_control

from freeform.agents.distill import bank_from_checkpoint
from freeform.agents.distill.teachers import TeacherBank
from freeform.checkpoint import load_checkpoint
from freeform.config import compose
from freeform.run.teacher_runs import main, pool_teacher_runs

TEACH = ("control.teachers=2", "control.controller=context", "agent.group_baseline=true", "control.headings=any",
         "agent.advantage_norm=group", "trainer.epochs=1")

WIDE = np.zeros((3, 3, 3), np.uint8)
WIDE[:, :2, 0] = 3
WIDE[0, 0, 0] = 2


def _teacher_run(tmp_path: Path, name: str, grids: np.ndarray, *overrides: str) -> Path:
    from freeform.train import train

    bodies = tmp_path / f"{name}.npy"
    np.save(bodies, grids)
    train(compose(*tiny_control(bodies, *TEACH, *overrides)), tmp_path / name)
    return tmp_path / name


def _bank(run: Path) -> TeacherBank:
    return bank_from_checkpoint(load_checkpoint(run / "checkpoints" / "last.pt"), str(run))


def _holds(pool: TeacherBank, sources: list[tuple[TeacherBank, int]]) -> None:
    """The pool's teacher j has the weights of teacher m of bank b, ``(b, m) = sources[j]``."""
    for j, (bank, m) in enumerate(sources):
        mine, theirs = pool.member_state(j), bank.member_state(m)
        assert all(torch.equal(mine[k], theirs[k]) for k in theirs), j


def test_pooled_teachers_are_their_runs_teachers_and_teach_a_student(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from freeform.run.build import build

    a = _teacher_run(tmp_path, "a", np.stack([ROD, CUBE]), "seed=4", "control.body_seed=7")  # (unused by a .npy:
    b = _teacher_run(tmp_path, "b", np.stack([WIDE, ROD]), "seed=5")                     # the student's default)
    out = tmp_path / "pool"
    main([str(a), str(b), "--out", str(out)])
    assert "4 teachers from 2 runs" in capsys.readouterr().out
    np.testing.assert_array_equal(np.load(out / "bodies.npy"), np.stack([ROD, CUBE, WIDE, ROD]))
    pooled, bank_a, bank_b = _bank(out), _bank(a), _bank(b)
    assert pooled.teachers == 4
    _holds(pooled, [(bank_a, 0), (bank_a, 1), (bank_b, 0), (bank_b, 1)])
    assert not all(torch.equal(v, bank_b.member_state(0)[k]) for k, v in bank_a.member_state(0).items())
    assert json.loads((out / "pooled.json").read_text())["sources"][1]["teachers"] == [2, 4]

    # a student of the pool: each environment's label is its body's teacher's, the one its source run trained
    student = compose(*tiny_control(out / "bodies.npy", *TEACH[1:], "control.teachers=4", "env.num_envs=4",
                                    "algo=distill", f"algo.teacher={out}", "seed=4"))
    env, learner = build(student, torch.device("cpu"))
    obs = env.reset()
    labels = learner.teacher(obs, torch.arange(4))
    for i, (bank, m) in enumerate([(bank_a, 0), (bank_a, 1), (bank_b, 0), (bank_b, 1)]):
        alone = bank({"teacher": torch.tensor([m]), "policy": obs["policy"][i:i + 1]})
        torch.testing.assert_close(labels[0][i:i + 1], alone[0])
    # the bodies are checked against those the pool stored: its file changed, the student is refused
    np.save(out / "bodies.npy", np.stack([CUBE, ROD, WIDE, ROD]))
    with pytest.raises(ValueError, match=r"its bodies are not this run's \(bodies \[0, 1\] differ"):
        build(student, torch.device("cpu"))


def test_teachers_taken_from_one_run_are_its_teachers_on_their_bodies(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    from freeform.run.build import build

    a = _teacher_run(tmp_path, "a", np.stack([ROD, CUBE, WIDE]), "control.teachers=3", "env.num_envs=6", "seed=4")
    out = tmp_path / "taken"
    main([str(a), "--teachers", "2,0", "--out", str(out)])
    assert "2 teachers from 1 runs" in capsys.readouterr().out
    np.testing.assert_array_equal(np.load(out / "bodies.npy"), np.stack([WIDE, ROD]))
    taken, bank_a = _bank(out), _bank(a)
    assert taken.teachers == 2
    _holds(taken, [(bank_a, 2), (bank_a, 0)])
    assert not all(torch.equal(v, bank_a.member_state(1)[k]) for k, v in taken.member_state(0).items())
    assert json.loads((out / "pooled.json").read_text())["sources"][0]["taken"] == [2, 0]
    student = compose(*tiny_control(out / "bodies.npy", *TEACH[1:], "control.teachers=2", "env.num_envs=4",
                                    "algo=distill", f"algo.teacher={out}", "seed=4"))
    build(student, torch.device("cpu"))  # (its bodies and teachers are a teacher run's, checked as any)
    with pytest.raises(ValueError, match=r"--teachers \[0, 3\]: .* has teachers 0 … 2"):
        pool_teacher_runs([a], tmp_path / "bad", [0, 3])
    with pytest.raises(ValueError, match="from one teacher run"):
        pool_teacher_runs([a, a], tmp_path / "bad", [0])
    with pytest.raises(SystemExit):
        main([str(a), "--teachers", "0,x", "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def test_a_pool_refuses_other_tasks_other_controllers_and_a_used_folder(tmp_path: Path) -> None:
    a = _teacher_run(tmp_path, "a", np.stack([ROD, CUBE]), "seed=4")
    short = _teacher_run(tmp_path, "short", np.stack([ROD, CUBE]), "control.duration=0.025")
    wide = _teacher_run(tmp_path, "wide", np.stack([ROD, CUBE]), "control.hidden=6")
    with pytest.raises(ValueError, match=r"control\.duration differ"):
        pool_teacher_runs([a, short], tmp_path / "p1")
    light = _teacher_run(tmp_path, "light", np.stack([ROD, CUBE]), "sim.gravity=-1.0")
    with pytest.raises(ValueError, match=r"the physics: sim\.gravity: -1\.0 in .*light, -9\.81 in .*a differ"):
        pool_teacher_runs([a, light], tmp_path / "p1")
    with pytest.raises(ValueError, match=r"differ in \['controller', 'controller.hidden'\]"):
        pool_teacher_runs([a, wide], tmp_path / "p2")
    conv_a = _teacher_run(tmp_path, "conv_a", np.stack([ROD, CUBE]), "control.controller=conv")
    conv_b = _teacher_run(tmp_path, "conv_b", np.stack([WIDE, ROD]), "control.controller=conv")
    with pytest.raises(ValueError, match=r"differ in \['controller', 'controller.box'\]"):  # (conv: the padding
        pool_teacher_runs([conv_a, conv_b], tmp_path / "p5")                                # changes its commands)
    with pytest.raises(ValueError, match="at least two teacher runs"):
        pool_teacher_runs([a], tmp_path / "p3")
    with pytest.raises(ValueError, match="no teacher run or checkpoint"):
        pool_teacher_runs([a, tmp_path / "nowhere"], tmp_path / "p4")
    used = tmp_path / "used"
    used.mkdir()
    (used / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="already holds files"):
        pool_teacher_runs([a, a], used)
    assert [p.name for p in used.iterdir()] == ["notes.txt"] and (used / "notes.txt").read_text() == "mine"
    with pytest.raises(ValueError, match="already holds files"):
        pool_teacher_runs([a, a], used / "notes.txt")
    assert not any((tmp_path / p).exists() for p in ("p1", "p2", "p3", "p4", "p5"))


def test_one_teacher_exports_as_its_bodys_own_controller(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--teacher I``: teacher I's weights, the run's episode and body I as a ``controller.pt`` any controller tool
    reads; another index, several runs or a used folder are refused, and nothing there is overwritten."""
    from freeform.agents.controller_file import read_controller

    run = _teacher_run(tmp_path, "t", np.stack([ROD, CUBE]), "seed=3")
    out = tmp_path / "cube"
    main([str(run), "--teacher", "1", "--out", str(out)])
    assert "teacher 1 of" in capsys.readouterr().out
    np.testing.assert_array_equal(np.load(out / "body.npy"), CUBE[None])
    saved, bank = read_controller(out), _bank(run)
    theirs = bank.member_state(1)
    assert all(torch.equal(saved.controller.state_dict()[k], v) for k, v in theirs.items())
    assert not all(torch.equal(bank.member_state(0)[k], v) for k, v in theirs.items())  # (teacher 1, not 0)
    assert saved.control.headings == "any" and saved.kind == "context"

    with pytest.raises(ValueError, match=r"--teacher 2: .* teachers 0 … 1"):
        main([str(run), "--teacher", "2", "--out", str(tmp_path / "none")])
    with pytest.raises(ValueError, match="already holds files"):
        main([str(run), "--teacher", "0", "--out", str(out)])
    assert sorted(p.name for p in out.iterdir()) == ["body.npy", "controller.pt"]
    with pytest.raises(SystemExit):
        main([str(run), str(run), "--teacher", "0", "--out", str(tmp_path / "two")])
    assert not (tmp_path / "none").exists() and not (tmp_path / "two").exists()


def test_the_reptile_step_moves_the_start_along_its_teachers_mean_step(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """``--reptile --step E``: a bank started from one controller (``control.controller_init``) gives
    start + E · (mean of its teachers − start), weight by weight, computed here from the bank's members; E = 1 is
    their average. A bad step, a run started from no controller, or a start of another kind are refused, and
    nothing is written."""
    from freeform.agents.controller_file import read_controller, save_controller
    from freeform.agents.networks.controllers import MLPController
    from freeform.envs.control import OBS_CHANNELS, ControlConfig

    first = _teacher_run(tmp_path, "first", np.stack([ROD, CUBE]), "seed=3")
    main([str(first), "--teacher", "0", "--out", str(tmp_path / "start")])
    run = _teacher_run(tmp_path, "bank", np.stack([ROD, CUBE]), "seed=4",
                       f"control.controller_init={tmp_path / 'start'}")
    start, bank = read_controller(tmp_path / "start").controller.state_dict(), _bank(run)
    members = [bank.member_state(i) for i in range(2)]
    assert not all(torch.equal(members[0][k], members[1][k]) for k in start)  # (the teachers trained apart)
    for step in (1.0, 2.5):
        out = tmp_path / f"reptile{step}"
        main([str(run), "--reptile", "--step", str(step), "--out", str(out)])
        assert "the Reptile step" in capsys.readouterr().out
        got = read_controller(out).controller.state_dict()
        for k, w0 in start.items():
            want = w0 + step * ((members[0][k] + members[1][k]) / 2 - w0)
            torch.testing.assert_close(got[k], want, rtol=1e-6, atol=1e-7)
        assert json.loads((out / "reptile.json").read_text())["step"] == step

    for bad in ("0", "inf"):
        with pytest.raises(ValueError, match=f"--step {float(bad)}: .* positive, finite"):
            main([str(run), "--reptile", "--step", bad, "--out", str(tmp_path / "none")])
    with pytest.raises(SystemExit):  # (--step without --reptile: refused, not a silent pool)
        main([str(run), "--step", "3", "--out", str(tmp_path / "none")])
    with pytest.raises(ValueError, match=r"did not start from one controller .* give --start"):
        main([str(first), "--reptile", "--out", str(tmp_path / "none")])
    other = tmp_path / "mlp.pt"
    save_controller(other, MLPController(len(OBS_CHANNELS), (2, 1, 1), 2, (4,)), ControlConfig())
    with pytest.raises(ValueError, match=r"--start .*mlp.pt: a MLPController, and the teachers .* are "
                                         r"ContextConvControllers"):
        main([str(run), "--reptile", "--start", str(other), "--out", str(tmp_path / "none")])
    with pytest.raises(SystemExit):
        main([str(run), str(run), "--reptile", "--out", str(tmp_path / "none")])
    assert not (tmp_path / "none").exists()
