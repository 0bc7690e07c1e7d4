"""Teacher runs trained apart, pooled into one that a student is distilled from (issue 56).

A teacher run (``experiment=control_teachers_cpu``) trains one controller per body for M bodies; its cost grows
with M, so teachers for many bodies come from several runs — on other body sets, in other sessions, or as parallel
jobs of a cluster. ``pool_teacher_runs`` writes one teacher run of all their teachers, in order, that
``algo=distill`` reads as it reads any (``algo.teacher=OUT``):

    python -m freeform.run.teacher_runs runs/teachers_a runs/teachers_b --out runs/teachers_ab
    freeform-train experiment=control_student_cpu algo.teacher=runs/teachers_ab \\
        control.bodies=runs/teachers_ab/bodies.npy control.teachers=<M_a + M_b> env.num_envs=<a multiple of it>

``OUT`` holds ``bodies.npy`` (uint8 ``[ΣM, ρ, ρ, ρ]``: each run's bodies as it trained on them),
``checkpoints/last.pt`` (the pooled bank, its bodies, and a config whose ``control.bodies`` names that file: a student's
bodies are checked against the bodies stored, grid for grid) and ``pooled.json``
(where each teacher came from). The runs must hold the same kind of controller built alike, and have trained with
the same episode, simulator and grid settings: a student is taught one task.

One teacher out of a run, as a controller of its own (``export_teacher``): body I's controller — e.g. the committed
student adapted to your bodies (``experiment=control_adapt_cpu``) — as a self-contained ``controller.pt`` beside its
body (``body.npy``), which every controller tool reads (``lab.control --evaluate``, renders, co-design's
``control.controller_init``):

    python -m freeform.run.teacher_runs runs/adapt --teacher 3 --out runs/body3_controller

Some teachers of one run, as a teacher run of their own (the teachers of the bodies one expert won, which that
expert is distilled from: ``lab.experts``):

    python -m freeform.run.teacher_runs runs/teachers --teachers 0,3,5 --out runs/teachers_035

The Reptile step of a bank whose teachers all started from one controller (``reptile_step``): that start moved E
times along the teachers' mean weight step, a new student without a distillation:

    python -m freeform.run.teacher_runs runs/adapt --reptile --step 3 --out runs/reptile
"""

from __future__ import annotations

import argparse
import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

POOLED = "pooled.json"
"""The pooled run's provenance: each source run, its teachers' range in the pool and its epoch."""


def _source(run: Path) -> Any:
    """A teacher run (``freeform.run.build.TeacherRun``), as many bodies as teachers."""
    from freeform.run.build import read_teacher_run

    source = read_teacher_run(run, str(run))
    if len(source.bodies) != source.bank.teachers:
        raise ValueError(f"{run}: {source.bank.teachers} teachers and {len(source.bodies)} bodies (its records or "
                         "control.bodies hold fewer bodies than it has teachers)")
    return source


def _refuse_used(out: Path) -> None:
    """Refuse an ``--out`` that holds anything: what this module writes never overwrites."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"--out {out} already holds files: give an empty or new folder (nothing is overwritten)")


def _same_task(a: Any, b: Any, run: Path, run0: Path) -> None:
    """``b`` (a run's ``TrainConfig``) trained the same task as ``a``: the episode's settings, the simulator, the
    grid (its physics: the schedule may differ); refused naming what differs."""
    from freeform.envs.control import ControlEnv

    assert a.control is not None and b.control is not None
    differ = [f"control.{k}" for k, v in vars(a.control.episode()).items() if getattr(b.control, k) != v]
    differ += [f"env.{k}" for k in ("resolution",) if getattr(a.env, k) != getattr(b.env, k)]
    differ += [f"task.{k}" for k in ("materials",) if getattr(a.task, k) != getattr(b.task, k)]
    physics = ControlEnv.physics_differences(b.sim, a.sim, a.control.episode(), str(run), f"in {run0}")
    differ += [f"the physics: {physics}"] if physics else []  # (how it runs, the schedule, may differ)
    if differ:
        raise ValueError(f"{run} trained with other settings than {run0} ({', '.join(differ)} differ): a pool's "
                         "teachers must share the episode, simulator and grid")


def pool_teacher_runs(runs: list[Path], out: Path, teachers: list[int] | None = None) -> Path:
    """Write one teacher run in ``out`` holding every teacher of ``runs``, in order (module docstring) — or, of one
    run, its ``teachers`` alone, in that order (the teachers of the bodies an expert won: ``lab.experts``); returns
    ``out``. ``out`` must not hold anything yet (nothing is overwritten)."""
    from freeform.agents.distill.teachers import TeacherBank
    from freeform.checkpoint import CHECKPOINT_DIR, LAST, save_checkpoint
    from freeform.config import ControlRunConfig, from_container

    if teachers is None and len(runs) < 2:
        raise ValueError(f"give at least two teacher runs to pool (or one and the teachers to take), got {len(runs)}")
    if teachers is not None and len(runs) != 1:
        raise ValueError(f"teachers are taken from one teacher run, got {len(runs)}")
    _refuse_used(out)
    sources = [_source(run) for run in runs]
    for run, source in zip(runs[1:], sources[1:], strict=True):
        _same_task(sources[0].config, source.config, run, runs[0])
    shapes = [list(s.bodies.shape[1:]) for s in sources]
    if any(s != shapes[0] for s in shapes):
        raise ValueError(f"the runs' bodies are grids of different sizes ({shapes}): a pool's bodies share a grid")
    if teachers is not None:
        try:
            bank = sources[0].bank.select(teachers)
        except ValueError as e:
            raise ValueError(f"--teachers {teachers}: {runs[0]} has teachers 0 … {sources[0].bank.teachers - 1}: give "
                             "at least one of them") from e
        bodies = sources[0].bodies[torch.tensor(teachers)].numpy()
    else:
        bank = TeacherBank.concatenate([s.bank for s in sources])
        bodies = torch.cat([s.bodies for s in sources]).numpy()

    config = copy.deepcopy(sources[0].payload["config"])
    copies = config["env"]["num_envs"] // config["control"]["teachers"]
    defaults = ControlRunConfig()  # (what a .npy of bodies leaves unused: a student need not copy the first run's)
    config["control"].update(teachers=bank.teachers, bodies=str(out / "bodies.npy"), body_seed=defaults.body_seed,
                             top=defaults.top)
    config["env"]["num_envs"] = bank.teachers * copies
    from_container(config)  # (validated as any run's)

    provenance, start = [], 0
    for run, source in zip(runs, sources, strict=True):
        count = source.bank.teachers if teachers is None else len(teachers)
        provenance.append({"run": str(run), "teachers": [start, start + count], "epoch": source.payload.get("epoch"),
                           **({"taken": [int(t) for t in teachers]} if teachers is not None else {})})
        start += count
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "bodies.npy", bodies)
    save_checkpoint(out / CHECKPOINT_DIR / LAST, {
        "policy_class": sources[0].payload["policy_class"], "policy_kwargs": bank.init_kwargs,
        "ppo": {"policy": bank.state_dict()}, "config": config, "epoch": None, "pooled_from": provenance,
        "bodies": torch.from_numpy(bodies)})  # (what the bodies' check compares with, whatever the file becomes)
    (out / POOLED).write_text(json.dumps({"teachers": bank.teachers, "sources": provenance}, indent=1) + "\n")
    return out


def export_teacher(run: Path, teacher: int, out: Path) -> Path:
    """Write teacher ``teacher`` of the teacher run ``run`` into ``out`` (new or empty) as ``controller.pt``
    (``freeform.agents.controller_file.save_controller``: its weights, the run's episode and simulator) and its body
    as ``body.npy`` (uint8 ``[1, ρ, ρ, ρ]``); returns the controller file."""
    from freeform.agents.controller_file import save_controller

    _refuse_used(out)
    source = _source(run)
    if not 0 <= teacher < source.bank.teachers:
        raise ValueError(f"--teacher {teacher}: {run} has teachers 0 … {source.bank.teachers - 1}")
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "body.npy", source.bodies[teacher:teacher + 1].numpy().astype(np.uint8))
    return save_controller(out / "controller.pt", source.bank.member(teacher), source.config.control,
                           source.config.sim)


def reptile_step(run: Path, out: Path, step: float = 1.0, start: Path | None = None) -> Path:
    """The Reptile step (Nichol, Achiam & Schulman 2018) of a teacher run whose teachers all started from one
    controller: ``start + step · (mean of the teachers' weights − start)``, written into ``out`` (new or empty) as
    ``controller.pt`` with ``reptile.json`` (its provenance); returns the controller file. ``step`` = 1 is the
    teachers' weight average; ``start``: that controller (default: the run's ``control.controller_init``).

    A bank re-started from a student (``experiment=control_adapt_cpu``) trains its teachers apart; their mean step
    is what a few epochs on every body agree on, and a step along it is a new student without a distillation."""
    from freeform.agents.controller_file import read_controller, save_controller
    from freeform.agents.networks.controllers import PrivilegedCritic
    from freeform.run.build import controller_source

    if not (step > 0 and math.isfinite(step)):
        raise ValueError(f"--step {step}: the Reptile step is a positive, finite multiple of the teachers' mean step")
    _refuse_used(out)
    source = _source(run)
    start = start if start is not None else source.config.control.controller_init
    if start is None:
        raise ValueError(f"{run}: its teachers did not start from one controller (control.controller_init unset): "
                         "give --start, the controller they started from")
    begun, controller = read_controller(controller_source(str(start))), source.bank.member(0)
    if isinstance(controller, PrivilegedCritic):
        raise ValueError(f"{run}: its teachers carry a privileged critic (control.privileged_critic); the Reptile "
                         "step averages plain controllers only")
    if type(begun.controller) is not type(controller):
        raise ValueError(f"--start {start}: a {type(begun.controller).__name__}, and the teachers of {run} are "
                         f"{type(controller).__name__}s: give the controller they started from")
    mean, w0 = source.bank.mean_state(), begun.controller.state_dict()
    if set(w0) != set(mean) or any(w0[k].shape != v.shape for k, v in mean.items()):
        raise ValueError(f"--start {start}: its weights are not shaped as the teachers' of {run} (another width, "
                         "head or box): give the controller they started from")
    controller.load_state_dict({k: w0[k] + step * (v - w0[k]) for k, v in mean.items()})
    out.mkdir(parents=True, exist_ok=True)
    (out / "reptile.json").write_text(json.dumps({"run": str(run), "epoch": source.payload.get("epoch"),
                                                  "teachers": source.bank.teachers, "start": str(start),
                                                  "step": step}, indent=1) + "\n")
    return save_controller(out / "controller.pt", controller, source.config.control, source.config.sim)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="teacher runs (their directories or checkpoints), in the pool's order")
    p.add_argument("--out", required=True, help="a new folder for the pooled teacher run (or the exported teacher)")
    p.add_argument("--teacher", type=int, default=None, metavar="I",
                   help="export teacher I of the one run given as a controller.pt (with its body.npy) instead")
    p.add_argument("--teachers", default=None, metavar="I,J,...",
                   help="write a teacher run of these teachers of the one run given (in this order) instead")
    p.add_argument("--reptile", action="store_true",
                   help="write the Reptile step of the one run given (teachers started from one controller) instead")
    p.add_argument("--step", type=float, default=None, help="with --reptile: the step, a multiple of the teachers' "
                                                           "mean step (1: their weight average)")
    p.add_argument("--start", type=Path, default=None, help="with --reptile: the controller the teachers started "
                                                            "from (default: the run's control.controller_init)")
    args = p.parse_args(argv)
    if args.teachers is not None and (args.teacher is not None or args.reptile):
        p.error("--teachers writes a teacher run; --teacher and --reptile write a controller: give one of them")
    if not args.reptile and (args.step is not None or args.start is not None):
        p.error("--step and --start belong to --reptile")
    if args.reptile:
        if len(args.runs) != 1 or args.teacher is not None:
            p.error("--reptile takes one teacher run, without --teacher")
        step = 1.0 if args.step is None else args.step
        path = reptile_step(Path(args.runs[0]), Path(args.out), step, args.start)
        print(f"the Reptile step {step:g} of {args.runs[0]} -> {path}; a start for the next bank with "
              f"control.controller_init={path.parent}")
        return
    if args.teacher is not None:
        if len(args.runs) != 1:
            p.error(f"--teacher exports from one teacher run, got {len(args.runs)}")
        path = export_teacher(Path(args.runs[0]), args.teacher, Path(args.out))
        print(f"teacher {args.teacher} of {args.runs[0]} -> {path}; evaluate with python -m lab.control "
              f"--evaluate {path.parent} --bodies {path.parent / 'body.npy'}")
        return
    if args.teachers is not None:
        if len(args.runs) != 1:
            p.error(f"--teachers takes teachers from one teacher run, got {len(args.runs)}")
        try:
            chosen = [int(t) for t in args.teachers.split(",")]
        except ValueError:
            p.error(f"--teachers takes teacher indices separated by commas (0,3,5), got {args.teachers!r}")
        if len(set(chosen)) < len(chosen):
            p.error(f"--teachers {args.teachers}: each teacher once")
    out = pool_teacher_runs([Path(r) for r in args.runs], Path(args.out),
                            chosen if args.teachers is not None else None)
    pooled = json.loads((out / POOLED).read_text())
    print(f"{pooled['teachers']} teachers from {len(pooled['sources'])} runs -> {out}; distil with "
          f"algo.teacher={out} control.bodies={out / 'bodies.npy'} control.teachers={pooled['teachers']}")


if __name__ == "__main__":
    main()
