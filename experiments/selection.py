"""Each body the best of several controllers, chosen by one trial each (few-shot selection, no learning)::

    python -m experiments.selection TABLE_A TABLE_B ... --out DIR [--names A B ...]

The tables are held-out tables of the same bodies (``python -m experiments.control --evaluate ... --bodies`` or
``experiments.heldout --pool`` output folders, or ``heldout93/<name>_bodies.csv`` as the results keep them), one per
controller. A body's trial is its table's mean-command episode: the simulator and a controller's mean command are
deterministic on one host and build (two evaluation episodes of one body give the same figure to the bit), so the
episode that chooses a body's controller is the episode that controller then walks there — the chosen figure is
what a user who tries each controller once on the body and keeps the best gets on that host, not an optimistic draw.
Across hosts the fast-math step moves a body's figure (the committed student's two tables of the 93, two AVX-512
hosts: median |Δ| 4e-4, one body 0.22), which makes a choice among tables of two hosts a little optimistic (≈ 0.1
point of per-body control for the best of 17, estimated). The stochastic column has no such property (the best of
noisy draws is biased upwards) and is not selected on, nor are tables along random headings (one draw of headings a
body; refused where the table's ``run.json`` records the task, warned where it does not).

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

import numpy as np

from experiments.common import missing_figure, summary_row, write_rows
from experiments.paired import read_table, same_bodies, set_files, table_run, warn_hosts

MADE_BY = "python -m experiments.control --evaluate ... --bodies, or experiments.heldout --pool"
REFERENCES = ("open_loop", "hand_set_wave", "per_body_mean_command")
"""The columns that describe a body rather than a controller, taken from the first table."""


def best_of_k(values: np.ndarray, k: int) -> np.ndarray:
    """The expected best of ``k`` controllers drawn at random without replacement among C: ``values`` ``[C, M]``
    (each controller's figure on each of M bodies) → ``[M]``. With a body's figures sorted, v₍₁₎ ≤ … ≤ v₍C₎,
    the i-th is the best of a k-subset when the subset holds it and k − 1 of the i − 1 below it:
    E = Σᵢ v₍ᵢ₎ · C(i − 1, k − 1) / C(C, k). k = 1 is the controllers' mean, k = C their best."""
    values = np.asarray(values, dtype=np.float64)
    count = _check_k(values, k)
    weights = np.array([comb(i, k - 1) for i in range(count)], dtype=np.float64) / comb(count, k)
    return weights @ np.sort(values, axis=0)


def beyond_best_of_k(values: np.ndarray, gaits: np.ndarray, k: int) -> float:
    """The expected fraction of bodies on which the best of ``k`` random controllers among C moves beyond the body's
    own gait (``values`` ``[C, M]``, ``gaits`` ``[M]``): the best fails only when all k are among the n_b
    controllers at or below the gait, with probability C(n_b, k) / C(C, k)."""
    count = _check_k(values, k)
    fails = np.array([comb(n, k) for n in range(count + 1)], dtype=np.float64) / comb(count, k)  # [n_b = 0 … C]
    return float(np.mean(1.0 - fails[(np.asarray(values) <= np.asarray(gaits)[None]).sum(0)]))


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
    checked to hold the same bodies in the same order (:func:`experiments.paired.same_bodies`)."""
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


def select(tables: list[Path], out: Path, names: list[str] | None = None) -> list[dict]:
    """Choose each body's controller among ``tables`` (one per controller, named ``names`` or by their files; a tie
    goes to the earlier table) and write the module's tables to ``out``. Returns ``best_of_k.csv``'s rows."""
    if len(tables) < 2:
        raise ValueError(f"select among at least two controllers' tables, got {len(tables)}")
    names = names or [table_name(t) for t in tables]
    if len(names) != len(tables) or len(set(names)) != len(names):
        raise ValueError(f"--names: one distinct name a table ({len(tables)} tables), got {names}")
    runs = [table_run(t) for t in tables]
    _check_task(tables, runs)
    tables_rows, values, body = _read(tables)
    first = tables_rows[0]
    files = [_controller_files(run, r) for run, r in zip(runs, tables_rows, strict=True)]
    choice = values.argmax(0)
    chosen = values[choice, np.arange(values.shape[1])]
    rows = [{"set": r.get("set", ""), "body": r["body"], **{c: float(body[c][i]) for c in body},
             **{f"mean_command_{n}": float(values[c, i]) for c, n in enumerate(names)},
             "chosen": names[choice[i]], "mean_command": float(chosen[i]), "controller_file": files[choice[i]][i]}
            for i, r in enumerate(first)]
    curve = [{"k": k, **_fractions(best_of_k(values, k), body, beyond_best_of_k(values, body["open_loop"], k))}
             for k in range(1, len(tables) + 1)]
    summary = [summary_row("chosen controller (mean command)", chosen),
               *({"what": what, "n": len(chosen), "mean": value} for what, value in _fractions(chosen, body).items()
                 if what != "mean"),
               *({"what": f"chosen: {n}", "n": len(chosen), "mean": float(np.mean(choice == c))}
                 for c, n in enumerate(names))]
    write_rows(out / "bodies.csv", rows)
    write_rows(out / "best_of_k.csv", curve)
    write_rows(out / "summary.csv", summary)
    record = {"tables": [str(t) for t in tables], "names": names, "bodies": len(first),
              "controllers": [run.get("controllers") or run.get("controller") for run in runs]}
    (out / "run.json").write_text(json.dumps(record, indent=1))
    return curve


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
    p = argparse.ArgumentParser(prog="python -m experiments.selection", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("tables", nargs="+", type=Path, help="held-out tables of the same bodies, one per controller")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--names", nargs="+", default=None, help="a name per table (default: the file's)")
    args = p.parse_args(argv)
    try:
        curve = select(args.tables, args.out, args.names)
    except ValueError as e:
        p.error(str(e))
    plot(curve, args.out / "best_of_k.png")
    for row in (curve[0], curve[-1]):
        shown = ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "k")
        print(f"best of {row['k']} (of {len(curve)}): {shown}")


if __name__ == "__main__":
    main()
