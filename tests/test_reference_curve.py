"""lab.reference: a per-body bank's convergence curve, each saved epoch's bank played on its bodies — the last point
each body's own controller played alone on that body."""

from __future__ import annotations

import csv

import numpy as np
import torch
from test_control_run import CUBE, ROD
from test_teacher_pool import WIDE, _teacher_run

from freeform.agents.distill import bank_from_checkpoint
from freeform.checkpoint import load_checkpoint
from freeform.control.play import play
from freeform.envs.control import ControlEnv
from freeform.run.build import read_teacher_run
from lab.reference import main, saved_epochs


def test_the_curve_reads_every_saved_epoch_and_ends_at_each_bodys_own_controller(tmp_path) -> None:
    run = _teacher_run(tmp_path, "t", np.stack([ROD, CUBE, WIDE]), "control.teachers=3", "env.num_envs=6",
                       "trainer.epochs=2", "seed=4")
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
    returns = load_checkpoint(run / "checkpoints" / "last.pt")["return_curve"]
    np.testing.assert_allclose(float(rows[-1]["training_return"]), returns[-1])
