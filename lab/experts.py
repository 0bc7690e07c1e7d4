"""Experts chosen by trial, trained as such: hard EM (``freeform.agents.distill.experts``) on a teacher run's bodies.

K experts (zoo names, ``controller.pt`` files or control runs) are tried on every body of the teacher run (one
episode each, mean command: ``freeform.control.fit.trials``); each body goes to the expert that moved it furthest;
each expert is distilled (``experiment=control_student_cpu``, DAgger, from the expert's own weights) from the
teachers of the bodies it won (``freeform.run.teacher_runs.pool_teacher_runs(..., teachers=...)``); again, until
no body changes expert or ``--rounds`` refits:

    python -m lab.experts --teachers runs/teachers64 --experts student,pool256,reptile3,wave --fixed wave \\
        --rounds 3 --epochs 10 --out runs/experts4

Writes ``OUT/round<r>/teachers<k>`` and ``OUT/round<r>/expert<k>`` (each refit: its teachers, its distillation run),
``OUT/rounds.csv`` (per round and expert: the bodies it won, their mean move under it), ``OUT/assignment.csv`` (per
body: its expert and move in every round) and ``OUT/expert<k>/controller.pt`` (the experts at the end), which
``freeform-control fit --candidates OUT/expert0/controller.pt,...`` tries on any bodies.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from freeform.agents.distill.experts import HardEM, hard_em
from freeform.tables import write_rows


def experts_on(run: Path, experts: list[str], out: Path, rounds: int, epochs: int, fixed: frozenset[str] = frozenset(),
               copies: int = 2, preset: str = "control_student_cpu", seed: int = 0,
               overrides: tuple[str, ...] = ()) -> HardEM[str]:
    """Hard EM of ``experts`` on the teacher run ``run``'s bodies (module docstring); returns its outcome, each
    expert a source ``read_controller`` reads. ``overrides``: more of the distillation's settings (KEY=VALUE)."""
    from freeform.agents.controller_file import read_controller, save_controller
    from freeform.config import compose
    from freeform.control.fit import Candidates, candidate_name, trials
    from freeform.run.build import read_teacher_run
    from freeform.run.teacher_runs import pool_teacher_runs
    from freeform.train import train
    from freeform.zoo import resolve
    from lab.heldout import episode_overrides

    names = [candidate_name(e) for e in experts]
    unknown = sorted(fixed - set(names))
    if unknown:
        raise ValueError(f"--fixed {unknown}: not among the experts {names}")
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"--out {out} holds files already: give a new folder (nothing is overwritten)")
    source = read_teacher_run(run, f"--teachers {run}")
    grids = source.bodies.to(torch.uint8)
    episode = episode_overrides(source.config.control.episode())
    done = {"trials": 0}

    def trial(current: list[str]) -> np.ndarray:
        c = Candidates(tuple(current), grids)
        _, moves = trials(c, grids, c.control.steps, seed)
        done["trials"] += 1
        print(f"round {done['trials'] - 1}: each expert's bodies and mean move "
              f"{[(int((moves.argmax(0) == k).sum()), round(float(moves[k].mean()), 3)) for k in range(len(current))]}",
              flush=True)
        return moves

    def refit(k: int, expert: str, bodies: np.ndarray) -> str:
        where = out / f"round{done['trials']}"  # (a run is named expert<k>: what fit's tables call it)
        teachers = pool_teacher_runs([run], where / f"teachers{k}", bodies.tolist())
        n = len(bodies)
        cfg = compose(f"experiment={preset}", f"algo.teacher={teachers}", f"control.bodies={teachers / 'bodies.npy'}",
                      f"control.teachers={n}", f"env.num_envs={n * copies}", f"control.controller_init={expert}",
                      f"trainer.epochs={epochs}", "trainer.render_every=0", "trainer.progress=false", f"seed={seed}", *episode,
                      *overrides)  # (the teachers' episode: a student is taught the task they learned)
        with torch.enable_grad():
            result = train(cfg, where / f"expert{k}")
        if result.stopped:  # (a stop signal: no EM goes on with a half-trained expert)
            raise SystemExit(f"expert {k}'s refit stopped ({result.stopped}) in {where / f'expert{k}'}; the EM "
                             f"is not resumable: run it again into a new --out")
        return str(where / f"expert{k}")

    em = hard_em(experts, trial, refit, rounds, [n in fixed for n in names])
    out.mkdir(parents=True, exist_ok=True)
    rows = [{"round": r, "expert": names[k], "bodies": int((h.assignment == k).sum()),
             "mean_move": float(h.moves[k][h.assignment == k].mean()) if (h.assignment == k).any() else float("nan"),
             "all_bodies_move": float(h.moves[k].mean())}
            for r, h in enumerate(em.history) for k in range(len(experts))]
    write_rows(out / "rounds.csv", rows)
    write_rows(out / "assignment.csv", [
        {"body": m, **{f"round{r}_expert": names[int(h.assignment[m])] for r, h in enumerate(em.history)},
         **{f"round{r}_move": float(h.moves[h.assignment[m], m]) for r, h in enumerate(em.history)}}
        for m in range(len(grids))])
    for k, e in enumerate(em.experts):
        saved = read_controller(resolve(e))  # (a zoo name too: an expert never refit, such as the wave)
        save_controller(out / f"expert{k}" / "controller.pt", saved.controller, saved.control, saved.sim)
    (out / "run.json").write_text(json.dumps({
        "teachers": str(run), "experts": experts, "fixed": sorted(fixed), "rounds": rounds, "epochs": epochs,
        "copies": copies, "preset": preset, "seed": seed, "overrides": list(overrides), "fixed_point": em.fixed_point,
        "refits": len(em.history) - 1}, indent=1) + "\n")
    return em


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--teachers", type=Path, required=True, help="a teacher run (its bodies are the EM's)")
    p.add_argument("--experts", required=True, help="the starting experts, comma-separated (zoo names or paths)")
    p.add_argument("--fixed", default="", help="experts never refit, comma-separated by name (e.g. wave)")
    p.add_argument("--rounds", type=int, default=3, help="refits at most (0: the first assignment alone)")
    p.add_argument("--epochs", type=int, default=10, help="distillation epochs a refit")
    p.add_argument("--copies", type=int, default=2, help="environments per body in a distillation")
    p.add_argument("--preset", default="control_student_cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more distillation settings")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    experts = [e for e in args.experts.split(",") if e]
    em = experts_on(args.teachers, experts, args.out, args.rounds, args.epochs,
                    frozenset(f for f in args.fixed.split(",") if f), args.copies, args.preset, args.seed,
                    tuple(args.set))
    print(f"{'a fixed point' if em.fixed_point else 'out of rounds'} after {len(em.history) - 1} refits; experts in "
          f"{args.out}/expert<k>/controller.pt")


if __name__ == "__main__":
    main()
