"""Each body the best of several controllers, chosen by one trial each (few-shot selection, no learning)::

    python -m lab.selection --try CONTROLLER_A CONTROLLER_B ... --bodies BODIES.npy --out DIR
        [--trial-decisions D] [--reference TABLE] [--names A B ...] [--headings any|fixed]
    python -m lab.selection TABLE_A TABLE_B ... --out DIR [--names A B ...]

With ``--try`` (:func:`try_controllers`) the controllers are played here, each by its mean command for one episode
on every body, all in one env (on the 2-core host, 17 students on the 93 held-out bodies in 3 min 38 s; their 17
evaluations, ``--eval-episodes 2``, which play six other groups beside the mean command, take about 2 min each),
and each body's controller is chosen by its move after ``D`` decisions (default: the whole episode), then scored by
its whole episode; ``moves.npy`` keeps every controller's move after each decision.
The bodies' own gaits and the hand-set wave come with it; ``--reference``, a held-out table of the same bodies
evaluated with ``--per-body``, adds the fraction of per-body control. ``DIR/bodies.csv``'s ``controller_file`` is the
file to drive each body with.

Without it, the tables are held-out tables of the same bodies (``python -m lab.control --evaluate ... --bodies``
or ``lab.heldout --pool`` output folders, or ``heldout93/<name>_bodies.csv`` as the results keep them), one per
controller. A body's trial is its table's mean-command episode: the simulator and a controller's mean command are
deterministic on one host and build (two evaluation episodes of one body give the same figure to the bit), so the
episode that chooses a body's controller is the episode that controller then walks there — the chosen figure is what a
user who tries each controller once on the body and keeps the best gets on that host, not an optimistic draw. Across
hosts the fast-math step moves a body's figure (the committed student's two tables of the 93, two AVX-512 hosts: median
|Δ| 4e-4, one body 0.22), which makes a choice among tables of two hosts a little optimistic (≈ 0.1 point of per-body
control for the best of 17, estimated). The stochastic column has no such property (the best of noisy draws is biased
upwards) and is not selected on, nor are tables along random headings (one draw of headings a body; refused where the
table's ``run.json`` records the task, warned where it does not).

Writes ``DIR/bodies.csv`` (per body: its set and index, own gait, the hand-set wave's and the per-body controller's
mean commands where the tables have them, each controller's mean command, the one chosen, its figure and
``controller_file``, the file its table's ``run.json`` records it was evaluated from — as recorded then: a file since
moved keeps its old path),
``DIR/best_of_k.csv`` (for k = 1 … C controllers, the mean over bodies of the expected best of k controllers drawn
at random among the C — exactly, not sampled: :func:`best_of_k` — with the fraction of per-body control, × the
hand-set wave and the fraction of bodies beyond their own gait), ``DIR/summary.csv`` (the chosen controllers' mean
with its 99 % band, the same fractions, how often each controller was chosen), ``DIR/run.json`` and the curve drawn,
``DIR/best_of_k.png``.
"""

from __future__ import annotations

import argparse
import json
import warnings
from math import comb
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from experiments.common import missing_figure, summary_row, write_rows
from freeform.agents.controller_file import controller_for, read_controller
from freeform.control.fit import episode_differences
from freeform.envs.control import ControlConfig, ControlEnv, open_loop_displacement, open_loop_moves
from freeform.sim import SimConfig
from lab.heldout import Evaluation, evaluated_control, hand_set_wave, play, read_bodies
from lab.paired import read_table, same_bodies, set_files, table_run, warn_hosts

MADE_BY = "python -m lab.control --evaluate ... --bodies, or lab.heldout --pool"
REFERENCES = ("open_loop", "hand_set_wave", "per_body_mean_command")
"""The columns that describe a body rather than a controller, taken from the first table."""


def best_of_k(values: np.ndarray, k: int, by: np.ndarray | None = None) -> np.ndarray:
    """The expected figure of the best of ``k`` controllers drawn at random without replacement among C: ``values``
    ``[C, M]`` (each controller's figure on each of M bodies) → ``[M]``; "best" by ``by`` ``[C, M]`` (a trial's
    figure, None: ``values`` themselves), a tie to the earlier controller. With a body's controllers ordered by ``by``,
    the i-th is chosen from a k-subset when the subset holds it and k − 1 of the i − 1 before it:
    E = Σᵢ v₍ᵢ₎ · C(i − 1, k − 1) / C(C, k). k = 1 is the controllers' mean, k = C the chosen one's figure."""
    return _choice_weights(values, k) @ _ordered(values, values if by is None else by)


def beyond_best_of_k(values: np.ndarray, gaits: np.ndarray, k: int, by: np.ndarray | None = None) -> float:
    """The expected fraction of bodies on which the best of ``k`` random controllers among C (by ``by``, as
    :func:`best_of_k`) moves beyond the body's own gait (``values`` ``[C, M]``, ``gaits`` ``[M]``)."""
    values = np.asarray(values, dtype=np.float64)
    beyond = _ordered(values, values if by is None else by) > np.asarray(gaits)[None]
    return float(np.mean(_choice_weights(values, k) @ beyond))


def _choice_weights(values: np.ndarray, k: int) -> np.ndarray:
    """[C]: the chance that the i-th of C ordered controllers is the last of a random k-subset, C(i, k − 1) / C(C, k)
    for i = 0 … C − 1."""
    count = _check_k(values, k)
    return np.array([comb(i, k - 1) for i in range(count)], dtype=np.float64) / comb(count, k)


def _ordered(values: np.ndarray, by: np.ndarray) -> np.ndarray:
    """``values`` [C, M] reordered on each body by ``by`` ascending, ties with the earlier controller last (so that
    the last of any subset is the one an argmax over it, in the controllers' order, picks)."""
    values, by = np.asarray(values, dtype=np.float64), np.asarray(by, dtype=np.float64)
    if by.shape != values.shape:
        raise ValueError(f"best of k: the trial's figures {by.shape} are not the values' {values.shape}")
    index = np.broadcast_to(np.arange(len(values))[:, None], values.shape)
    order = np.lexsort((-index, by), axis=0)
    return np.take_along_axis(values, order, axis=0)


def _check_k(values: np.ndarray, k: int) -> int:
    """The number of controllers C of ``values [C, M]``, refusing a k that is no subset's size."""
    count = np.shape(values)[0]
    if not 1 <= k <= count:
        raise ValueError(f"best of k: k must be in [1, {count}] (the controllers given), got {k}")
    return count


def _fractions(chosen: np.ndarray, body: dict[str, np.ndarray], beyond: float | None = None) -> dict[str, float]:
    """Mean-command figures of one choice against the bodies' references: the fraction of per-body control (sums,
    as the held-out tables' summary), × the hand-set wave, and the fraction of bodies beyond their own gait
    (``beyond`` where ``chosen`` is an expectation, whose own comparison with the gait would not be one)."""
    beyond = float(np.mean(chosen > body["open_loop"])) if beyond is None else beyond
    out = {"mean": float(chosen.mean()), "beyond_own_gait": beyond}
    if "per_body_mean_command" in body:
        out["fraction_of_per_body"] = float(chosen.sum() / body["per_body_mean_command"].sum())
    if "hand_set_wave" in body:
        out["over_hand_set_wave"] = float(chosen.mean() / body["hand_set_wave"].mean())
    return out


def _read(tables: list[Path]) -> tuple[list[list[dict[str, str]]], np.ndarray, dict[str, np.ndarray]]:
    """(each table's rows, each controller's mean command ``[C, M]``, the bodies' reference columns) of tables
    checked to hold the same bodies in the same order (:func:`lab.paired.same_bodies`)."""
    rows = [read_table(t, str(t), MADE_BY) for t in tables]
    for table, r in zip(tables, rows, strict=True):
        missing = [c for c in ("body", "open_loop", "mean_command") if not r or c not in r[0]]
        if missing:
            raise ValueError(f"{table}: no {missing} column (a held-out bodies table of {MADE_BY})")
        empty = next((row["body"] for row in r if missing_figure(row["mean_command"])), None)
        if empty is not None:
            raise ValueError(f"{table}: body {empty} has no mean command (an empty or NaN figure cannot be a trial)")
    warn_hosts([drift for table, r in zip(tables[1:], rows[1:], strict=True)
                for drift in same_bodies(rows[0], r, str(tables[0]), str(table), (set_files(tables[0]),
                                                                                   set_files(table)))])
    values = np.array([[float(row["mean_command"]) for row in r] for r in rows])
    return rows, values, _references(tables, rows)


def _controller_files(run: dict, rows: list[dict[str, str]]) -> list[str]:
    """The controller file each of a table's rows was evaluated with, from its ``run.json`` (``run``: a set's
    ``controller``, or a pooled table's ``controllers``, one per set folder of ``pooled``); "" where unrecorded."""
    if run.get("controller"):
        return [str(run["controller"])] * len(rows)
    pooled, files = run.get("pooled") or [], run.get("controllers") or []
    if len(pooled) != len(files):  # (a record that does not pair sets with files names none)
        return [""] * len(rows)
    by_set = {str(folder): "" if file is None else str(file) for folder, file in zip(pooled, files, strict=True)}
    return [by_set.get(r.get("set", ""), "") for r in rows]


def _check_task(tables: list[Path], runs: list[dict]) -> None:
    """Refuse tables along random headings (where their ``run.json``, ``runs``, records the task): one draw of
    headings a body, on which the best of several controllers is biased upwards for the next draw, so it is no
    trial. Tables that record no task (pooled before 2026-12-01) are warned about."""
    tasks = [(run.get("control") or {}).get("headings") for run in runs]
    drawn = [str(t) for t, task in zip(tables, tasks, strict=True) if task == "random"]
    if drawn:
        raise ValueError(f"{drawn[0]}: evaluated along random headings, one draw of them a body: the best of several "
                         "controllers on one draw is biased upwards on the next, so it is not a trial (select on "
                         "tables of a fixed task: --headings any or none)")
    unknown = [str(t) for t, task in zip(tables, tasks, strict=True) if task is None]
    if unknown:
        warnings.warn(f"{len(unknown)} of the tables ({unknown[0]}, ...) record no task in their run.json (pooled "
                      "before it was recorded): select on them only if they were evaluated along a fixed task "
                      "(--headings any or none), not random headings", stacklevel=3)


def _references(tables: list[Path], rows: list[list[dict[str, str]]]) -> dict[str, np.ndarray]:
    """Each of :data:`REFERENCES` from the first table that has it for every body (the same bodies: any table's
    figure is theirs); a column some table has for part of the bodies only (``--per-body N`` with N < M) is warned
    about and left out."""
    body: dict[str, np.ndarray] = {}
    for column in REFERENCES:
        present = [(t, r) for t, r in zip(tables, rows, strict=True) if column in r[0]]
        whole = next((r for _, r in present if not any(missing_figure(row[column]) for row in r)), None)
        if whole is not None:
            body[column] = np.array([float(row[column]) for row in whole])
        elif present:
            warnings.warn(f"{present[0][0]}: {column} is there for part of the bodies only; the fractions that need "
                          "it are left out (evaluate one table with --per-body M, every body)", stacklevel=3)
    return body


def table_name(table: Path) -> str:
    """A table's name: its folder's (``runs/try_gen4`` or ``runs/try_gen4/bodies.csv`` → ``try_gen4``), or its file's
    as the results keep one (``heldout93/student64_gen4_bodies.csv`` → ``student64_gen4``)."""
    if table.suffix != ".csv" or table.name == "bodies.csv":
        return (table.parent if table.suffix == ".csv" else table).name
    return table.name.removesuffix("_bodies.csv").removesuffix(".csv")


def controller_name(source: Path) -> str:
    """A controller's name: its folder's for a folder or a ``controller.pt`` (``iterated64/gen4/controller.pt`` →
    ``gen4``), its run's for a checkpoint (``runs/s64/checkpoints/last.pt`` → ``s64``), else the file's stem."""
    if source.suffix != ".pt":
        return source.name
    if source.parent.name == "checkpoints":
        return source.parent.parent.name
    return source.parent.name if source.name == "controller.pt" else source.stem


def select(tables: list[Path], out: Path, names: list[str] | None = None) -> list[dict]:
    """Choose each body's controller among ``tables`` (one per controller, named ``names`` or by their files; a tie
    goes to the earlier table) and write the module's tables to ``out``. Returns ``best_of_k.csv``'s rows."""
    if len(tables) < 2:
        raise ValueError(f"select among at least two controllers' tables, got {len(tables)}")
    names = _names(names, [table_name(t) for t in tables], "table")
    runs = [table_run(t) for t in tables]
    _check_task(tables, runs)
    tables_rows, values, body = _read(tables)
    files = [_controller_files(run, r) for run, r in zip(runs, tables_rows, strict=True)]
    record = {"tables": [str(t) for t in tables], "names": names, "bodies": len(tables_rows[0]),
              "controllers": [run.get("controllers") or run.get("controller") for run in runs]}
    return _choose(Choice(values, body, names, [{"set": r.get("set", ""), "body": r["body"]} for r in tables_rows[0]],
                          files), out, record)


def _names(names: list[str] | None, default: list[str], each: str) -> list[str]:
    """``--names`` (one distinct name ``each``: a table, a controller) or the default."""
    names = names or default
    if len(names) != len(default) or len(set(names)) != len(names):
        raise ValueError(f"--names: one distinct name a {each} ({len(default)} {each}s; give --names where the "
                         f"default names repeat), got {names}")
    return names


class Choice(NamedTuple):
    """What a choice is made from: the controllers' figures ``values`` [C, M] (mean command, whole episodes), the
    bodies' reference columns (:data:`REFERENCES`, [M] each), the controllers' names, each body's ``set`` and
    ``body``, each controller's file per body, and the trial ``by`` [C, M] it is chosen by (None: ``values``)."""

    values: np.ndarray
    body: dict[str, np.ndarray]
    names: list[str]
    keys: list[dict]
    files: list[list[str]]
    by: np.ndarray | None = None


def _choose(c: Choice, out: Path, record: dict) -> list[dict]:
    """Each body the controller whose trial moved it furthest (a tie to the earlier one), scored by its whole
    episode; writes ``out``'s tables (the module's docstring) and returns ``best_of_k.csv``'s rows."""
    by = c.values if c.by is None else c.by
    choice = by.argmax(0)
    chosen = c.values[choice, np.arange(c.values.shape[1])]
    trials = {} if c.by is None else {f"trial_{n}": c.by[i] for i, n in enumerate(c.names)}
    rows = [{**key, **{r: float(c.body[r][i]) for r in c.body},
             **{f"mean_command_{n}": float(c.values[j, i]) for j, n in enumerate(c.names)},
             **{t: float(v[i]) for t, v in trials.items()},
             "chosen": c.names[choice[i]], "mean_command": float(chosen[i]), "controller_file": c.files[choice[i]][i]}
            for i, key in enumerate(c.keys)]
    curve = [{"k": k, **_fractions(best_of_k(c.values, k, c.by), c.body,
                                   beyond_best_of_k(c.values, c.body["open_loop"], k, c.by))}
             for k in range(1, len(c.names) + 1)]
    summary = [summary_row("chosen controller (mean command)", chosen),
               *({"what": what, "n": len(chosen), "mean": value} for what, value in _fractions(chosen, c.body).items()
                 if what != "mean"),
               *({"what": f"chosen: {n}", "n": len(chosen), "mean": float(np.mean(choice == j))}
                 for j, n in enumerate(c.names))]
    write_rows(out / "bodies.csv", rows)
    write_rows(out / "best_of_k.csv", curve)
    write_rows(out / "summary.csv", summary)
    (out / "run.json").write_text(json.dumps(record, indent=1))
    return curve


@torch.no_grad()
def try_controllers(sources: list[Path], bodies: Path, out: Path, trial: int | None = None,
                    names: list[str] | None = None, headings: str | None = None,
                    reference: Path | None = None) -> list[dict]:
    """Play every controller of ``sources`` (``controller.pt`` files, folders holding one, or control runs) by its
    mean command, one episode on each body of ``bodies`` (:func:`lab.heldout.read_bodies`), all in one env
    — a block of rows a controller, the hand-set wave's block beside them where the actions are strokes — and
    choose each body's controller by its move after ``trial`` decisions (None: the whole episode), scored by its
    whole episode. The controllers must play the same episode (one ``ControlConfig`` and ``SimConfig``, the
    headings ``headings`` or their own, not random: one draw is no trial) in one box. ``reference``: a held-out
    table of the same bodies (checked body by body) whose per-body column gives the fraction of per-body control.
    Writes what :func:`select` writes (``bodies.csv`` with ``trial_<name>`` columns when ``trial`` is set) and
    ``moves.npy`` (float64 ``[C, decisions, M]``: each controller's move after each decision). Returns
    ``best_of_k.csv``'s rows."""
    if len(sources) < 2:
        raise ValueError(f"--try: at least two controllers to choose among, got {len(sources)}")
    names = _names(names, [controller_name(Path(s)) for s in sources], "controller")
    saved = [read_controller(Path(s)) for s in sources]
    sim = saved[0].sim or SimConfig()
    grids = read_bodies(bodies, len(sim.materials))
    saved = [controller_for(s.path, grids) for s in saved]
    control = _one_episode(saved, sim, headings)
    ref_rows = _reference_rows(reference, len(grids)) if reference is not None else None
    if trial is not None and not 1 <= trial <= control.steps:
        raise ValueError(f"--trial-decisions must be in [1, {control.steps}] (the episode's decisions), got {trial}")
    box = tuple(saved[0].controller.box)
    other = next((s for s in saved if tuple(s.controller.box) != box), None)
    if other is not None:
        raise ValueError(f"--try: {other.path} plays in box {tuple(other.controller.box)}, {saved[0].path} in {box}: "
                         "one env holds one box (try them apart)")
    m, nets = len(grids), [s.controller.eval() for s in saved]
    blocks = len(nets) + (control.stroke_periods >= 1)
    env = ControlEnv(grids.repeat(blocks, 1, 1, 1), sim=sim, control=control, seed=0, box=box,
                     first_env=np.tile(np.arange(m), blocks))
    groups = [(n, net, False, False) for n, net in zip(names, nets, strict=True)]
    if control.stroke_periods >= 1:
        groups.append(("hand_set_wave", hand_set_wave(env, nets[0], None), False, False))
    played = play(env, groups, control.steps, seed=0)
    body = {"open_loop": open_loop_displacement(grids, sim, control, headings=played.heading[:m],
                                                planar=control.headings == "any",
                                                moves=open_loop_moves(grids, sim, control))}
    if control.stroke_periods >= 1:
        body["hand_set_wave"] = played.returns[-1]
    keys = [{"set": "", "body": i} for i in range(m)]
    if ref_rows is not None:
        keys = _reference_columns(ref_rows, reference, body)
    after = played.after[:, : len(nets)].transpose(1, 0, 2)  # [C, decisions, M]
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "moves.npy", after)
    record = {"tried": [str(s.path) for s in saved], "names": names, "bodies": str(bodies), "body_count": m,
              "trial_decisions": trial, "decisions": control.steps, "reference": str(reference) if reference else None,
              "box": list(box), "control": vars(control)}
    return _choose(Choice(after[:, -1], body, names, keys, [[str(s.path)] * m for s in saved],
                          None if trial is None else after[:, trial - 1]), out, record)


def _one_episode(saved: list, sim: SimConfig, headings: str | None) -> ControlConfig:
    """The one episode every controller of ``saved`` is tried in: the first's ``ControlConfig`` along ``headings``
    (or its own; another task than it trained for warned, as the evaluation does), which every other controller's
    must equal, as its simulator's physics must ``sim``'s (``ControlEnv.physics_differences``: the schedule and backend
    may differ); random headings refused (the best of several controllers on
    one draw of headings is biased upwards on the next)."""
    control = evaluated_control(saved[0], Evaluation(episodes=1, headings=headings))  # (another task warned)
    if control.headings == "random":
        raise ValueError("--try along random headings: the best of several controllers on one draw of headings is "
                         "biased upwards on the next, so it is not a trial (--headings any or fixed)")
    for s in saved[1:]:
        if differ := episode_differences(s, control, sim, saved[0].path):
            raise ValueError(f"--try: {s.path} plays another episode than {saved[0].path} — {'; '.join(differ)}: "
                             "try controllers of one episode")
    return control


def _reference_rows(reference: Path, count: int) -> list[dict[str, str]]:
    """The rows of ``reference`` (a held-out table of the ``count`` bodies tried, in their order, with a per-body
    column for every body), refused before anything is played when it cannot be one."""
    rows = read_table(reference, f"--reference {reference}", MADE_BY)
    column = "per_body_mean_command"
    if len(rows) != count:
        raise ValueError(f"--reference {reference}: {len(rows)} bodies, not the {count} tried (a held-out table of the "
                         "same bodies, in the same order)")
    if "open_loop" not in rows[0]:
        raise ValueError(f"--reference {reference}: no open_loop column, by which its bodies are checked to be the ones "
                         f"tried (a held-out table of {MADE_BY})")
    if column not in rows[0] or any(missing_figure(r[column]) for r in rows):
        raise ValueError(f"--reference {reference}: no {column} for every body (evaluate it with --per-body M, "
                         "every body)")
    return rows


def _reference_columns(rows: list[dict[str, str]], reference: Path, body: dict[str, np.ndarray]) -> list[dict]:
    """Add the reference's per-body control column to ``body`` once its bodies are shown to be the ones tried
    (their own gaits, :func:`lab.paired.same_bodies`); returns its ``set`` and ``body`` keys."""
    mine = [{"set": r.get("set", ""), "body": r["body"], "open_loop": repr(float(g))}  # (its keys: gaits compared)
            for r, g in zip(rows, body["open_loop"], strict=True)]
    warn_hosts(same_bodies(rows, mine, str(reference), "the bodies tried"))
    body["per_body_mean_command"] = np.array([float(r["per_body_mean_command"]) for r in rows])
    return [{"set": r.get("set", ""), "body": r["body"]} for r in rows]


def plot(curve: list[dict], path: Path) -> None:
    """``best_of_k.csv`` drawn: the fraction of per-body control (or, without per-body columns, × the hand-set wave)
    and the fraction of bodies beyond their own gait against k."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = [row["k"] for row in curve]
    measure = "fraction_of_per_body" if "fraction_of_per_body" in curve[0] else "over_hand_set_wave"
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(k, [row[measure] for row in curve], "o-", color="k", label=measure.replace("_", " "))
    ax.plot(k, [row["beyond_own_gait"] for row in curve], "s--", color="0.5", label="bodies beyond their own gait")
    ax.axhline(1.0, color="0.8", lw=0.8)
    ax.set_xlabel("k: controllers tried once on each body, the best kept")
    ax.set_xticks(k)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m lab.selection", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("tables", nargs="*", type=Path, help="held-out tables of the same bodies, one per controller")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--names", nargs="+", default=None, help="a name per table or controller (default: the file's)")
    p.add_argument("--try", dest="tried", nargs="+", type=Path, default=None, metavar="CONTROLLER",
                   help="play these controllers on --bodies instead of reading tables")
    p.add_argument("--bodies", type=Path, default=None, help="with --try: the bodies (.npy)")
    p.add_argument("--trial-decisions", type=int, default=None,
                   help="with --try: choose by the move after this many decisions (default: the whole episode)")
    p.add_argument("--headings", choices=("any", "fixed"), default=None, help="with --try: the task (default: theirs)")
    p.add_argument("--reference", type=Path, default=None,
                   help="with --try: a held-out table of the same bodies with a per-body column")
    args = p.parse_args(argv)
    tried = args.tried is not None
    extra = [f"--{k.replace('_', '-')}" for k in ("bodies", "trial_decisions", "headings", "reference")
             if getattr(args, k) is not None]
    if tried == bool(args.tables) or (tried and args.bodies is None) or (not tried and extra):
        p.error("give tables, or --try CONTROLLER ... --bodies BODIES.npy, not both (--bodies, --trial-decisions, "
                f"--headings and --reference go with --try{'; got ' + ' '.join(extra) if extra and not tried else ''})")
    try:
        curve = (try_controllers(args.tried, args.bodies, args.out, args.trial_decisions, args.names, args.headings,
                                 args.reference) if tried else select(args.tables, args.out, args.names))
    except ValueError as e:
        p.error(str(e))
    plot(curve, args.out / "best_of_k.png")
    for row in (curve[0], curve[-1]):
        shown = ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "k")
        print(f"best of {row['k']} (of {len(curve)}): {shown}")


if __name__ == "__main__":
    main()
