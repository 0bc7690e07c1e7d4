"""The student's scaling curves (issue 56): held-out figures against the number of teachers it was distilled from,
against its distillation rounds (``--x rounds``), or against its generations of iterated distillation (``--x
generations``: teachers re-started from the last student, trained, distilled back into it), read from pooled
held-out tables (``python -m lab.heldout --pool ... --out DIR`` writes ``DIR/summary.csv``).

    python -m lab.student_scaling 64=runs/eval_s64_93 128=runs/eval_s128_93 256=runs/eval_s256_93 \\
        --out lab/results/control_student/scaling
    python -m lab.student_scaling --x rounds 2=runs/eval_s256r2_93 4=runs/eval_s256_93 8=runs/eval_s256r8_93 \\
        --out lab/results/control_student/scaling
    python -m lab.student_scaling --x generations 1=runs/eval_s64_attn_93 2=runs/eval_s64iter12_93 \\
        2=runs/eval_s64iter12s1_93 3=runs/eval_s64gen3_93 3=runs/eval_s64gen3s1_93 \\
        --out lab/results/control_student/scaling

Writes ``OUT/scaling.csv`` (``--x teachers``), ``OUT/rounds.csv`` or ``OUT/generations.csv`` (one row per point:
the x, bodies, the controller's stochastic and mean-command moves, their fractions of per-body control, the mean
command over the hand-set wave, the fraction of bodies beyond their own gait) and the figure beside it (``.png``). A
point's label is its x; two points may share one (seeds).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from experiments.common import read_rows, write_rows
from lab.paired import table_run

ROWS = {
    "stochastic": "controller (stochastic)",
    "mean_command": "controller (mean command)",
    "fraction_stochastic": "fraction of per-body control (stochastic)",
    "fraction_mean_command": "fraction of per-body control (mean command)",
    "over_wave": "controller (mean command) over the hand-set wave",
    "beyond_gait": "fraction of bodies beyond their own gait: controller (mean command)",
}
"""scaling.csv's columns -> the pooled summary's rows they are read from."""

AXES = {"teachers": ("scaling", "log"), "rounds": ("rounds", "log"), "generations": ("generations", "linear")}
"""What a point's label counts (``--x``) -> the files' stem and the x axis's scale: the number of teachers or of
distillation rounds (they double: 16, 64, 256; 2, 4, 8), or of generations (1, 2, 3: generation 1 distilled from
teachers started from the population controller, generation g + 1 from teachers started from generation g)."""


def read_point(label: str, folder: Path, x: str = "teachers") -> dict[str, float | int | str]:
    """One point: ``label`` (its ``x``: number of teachers or rounds) and the pooled summary in ``folder``, every
    row of :data:`ROWS` required (refused naming the first missing)."""
    try:
        value = int(label)
    except ValueError:
        raise ValueError(f"a point is {x.upper()}=FOLDER with {x.upper()} an integer, got {label!r}") from None
    summary = folder / "summary.csv"
    if not summary.is_file():
        raise ValueError(f"{folder}: no summary.csv there (write one with python -m lab.heldout --pool)")
    rows = {r["what"]: r for r in read_rows(summary)}
    point: dict[str, float | int | str] = {x: value, "folder": str(folder)}
    for column, what in ROWS.items():
        if what not in rows:
            raise ValueError(f"{summary}: no row {what!r} (evaluate with --per-body on every body, then --pool)")
        point[column] = float(rows[what]["mean"])
    point["bodies"] = int(rows[ROWS["mean_command"]]["n"])
    return point


def body_sets(folder: Path) -> list[tuple[str, int]] | None:
    """The sets a pooled table was made of, as (the ``.npy``'s file name, its body count), sorted; None for a
    table pooled before ``lab.heldout`` recorded them (only its count can then be compared)."""
    sets = table_run(folder).get("sets")
    if sets is None:
        return None
    return sorted((Path(str(s["bodies"])).name, int(s["n"])) for s in sets)


def same_bodies(points: list[dict], sets: list[list[tuple[str, int]] | None]) -> None:
    """Refuse points over other held-out bodies: their sets' files and counts where every point's table records
    them, else their body counts."""
    if all(s is not None for s in sets) and any(s != sets[0] for s in sets):
        other = next(i for i, s in enumerate(sets) if s != sets[0])
        raise SystemExit(f"{points[other]['folder']} pools other sets than {points[0]['folder']} ({sets[other]} "
                         f"against {sets[0]}): compare students on the same held-out bodies")
    if len({p["bodies"] for p in points}) != 1:
        raise SystemExit(f"the points are over different numbers of bodies ({[p['bodies'] for p in points]}): "
                         "compare students on the same held-out bodies")


def plot(points: list[dict], path: Path, x: str = "teachers") -> None:
    """Fraction of per-body control (both ways) and × the wave against ``x`` (the number of teachers, rounds or
    generations; log x where it doubles)."""
    from experiments.common import pyplot

    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5))
    ticks = sorted({p[x] for p in points})  # (the line through each count's mean over its seeds, every point shown)

    def curve(ax: Any, column: str, scale: float, style: str, label: str | None = None) -> None:
        mean = [scale * sum(p[column] for p in points if p[x] == t) / sum(p[x] == t for p in points) for t in ticks]
        line, = ax.plot(ticks, mean, style, label=label)
        ax.plot([p[x] for p in points], [scale * p[column] for p in points], ".", color=line.get_color())

    curve(left, "fraction_mean_command", 100, "o-", "mean command")
    curve(left, "fraction_stochastic", 100, "s--", "stochastic")
    left.axhline(70, color="grey", lw=0.8, ls=":", label="issue's bar (70 %)")
    scale = AXES[x][1]
    left.set(xscale=scale, xlabel=x, ylabel="% of per-body control", title="held-out bodies")
    curve(right, "over_wave", 1, "o-")
    right.axhline(1.5, color="grey", lw=0.8, ls=":")
    right.set(xscale=scale, xlabel=x, ylabel="× the hand-set wave (mean command)")
    for ax in (left, right):
        ax.set_xticks(ticks, [str(t) for t in ticks])
        ax.minorticks_off()
    left.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("points", nargs="+", help="X=FOLDER: a pooled held-out table and its student's teachers (or "
                                             "rounds or generations, with --x)")
    p.add_argument("--x", default="teachers", choices=list(AXES), help="what a point's label counts")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    points = []
    for arg in args.points:
        label, sep, folder = arg.partition("=")
        if not sep:
            raise SystemExit(f"a point is {args.x.upper()}=FOLDER, got {arg!r}")
        points.append(read_point(label, Path(folder), args.x))
    same_bodies(points, [body_sets(Path(p["folder"])) for p in points])
    points.sort(key=lambda p: p[args.x])
    out = Path(args.out)
    write_rows(out / f"{AXES[args.x][0]}.csv", [{k: p[k] for k in (args.x, "bodies", *ROWS, "folder")} for p in points])
    plot(points, out / f"{AXES[args.x][0]}.png", args.x)
    for q in points:
        print(f"{q[args.x]:5d} {args.x}: {100 * q['fraction_mean_command']:.1f} % of per-body (mean command), "
              f"x{q['over_wave']:.2f} the wave, {100 * q['beyond_gait']:.0f} % beyond their gait")


if __name__ == "__main__":
    main()
