"""Per-body control against its epochs of training, from two starts (issue 56): what a start is worth when each
held-out body then gets a controller of its own (``experiment=control_adapt_cpu``: the bank started from the
distilled student; ``control_teachers_cpu``: from the population controller).

Each point is a pooled held-out table (``python -m lab.heldout --pool``) whose ``--per-body-run`` was the
bank after EPOCHS epochs (a checkpoint, ``checkpoints/epoch_00000E.pt``). At 0 epochs a bank is its start, so a
0-epoch point reads the table's evaluated controller (the student, or the population controller) instead of its
per-body column:

    python -m lab.adaptation \\
        --from student 0=runs/eval_student_93 2=runs/eval_adapt02_93 4=runs/eval_adapt04_93 12=runs/eval_adapt12_93 \\
        --from population 0=runs/eval_population_93 4=runs/eval_ref04_93 12=runs/eval_student_93 \\
        --out lab/results/control_student/adaptation

Writes ``adaptation.csv`` (start, epochs, bodies, stochastic and mean-command moves with 99 % bands, the fraction
of bodies beyond their own gait), ``paired.csv`` (per body, the first start minus each other at the epochs both
have, 99 % bands) and ``adaptation.png``. Every table must hold the same bodies, in order.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from experiments.common import mean_band, paired_band, write_rows
from lab.paired import body_keys, read_table

COLUMNS = {"stochastic": ("controller", "per_body"), "mean_command": ("mean_command", "per_body_mean_command")}
"""A point's figures -> bodies.csv's columns they are read from: (at 0 epochs, after training)."""


def read_bodies(folder: Path, per_body: bool = True) -> list[dict[str, str]]:
    """``folder``'s per-body table (a pooled or single held-out evaluation), refused naming what is missing;
    ``per_body``: whether the point reads the per-body columns (after training; its 0-epoch point reads the start's)."""
    rows = read_table(folder, str(folder), "python -m lab.control --evaluate")
    if per_body and rows and "per_body" not in rows[0]:
        raise ValueError(f"{folder}: no per_body column (evaluate with --per-body N --per-body-run RUN)")
    return rows


def read_point(start: str, spec: str) -> dict:
    """``EPOCHS=FOLDER`` of the start ``start``: its per-body moves ``[n]`` both ways and the folder."""
    epochs, sep, folder = spec.partition("=")
    if not sep or not epochs.isdigit():
        raise ValueError(f"--from {start}: a point is EPOCHS=FOLDER with EPOCHS a whole number, got {spec!r}")
    at = 0 if int(epochs) == 0 else 1
    rows = read_bodies(Path(folder), per_body=at == 1)
    moves = {k: np.array([float(r[cols[at]]) for r in rows]) for k, cols in COLUMNS.items()}
    gait = np.array([float(r["open_loop"]) for r in rows])
    return {"start": start, "epochs": int(epochs), "folder": folder, "keys": body_keys(rows), "gait": gait, **moves}


def summary(point: dict) -> dict:
    """One row of adaptation.csv."""
    row = {"start": point["start"], "epochs": point["epochs"], "bodies": len(point["gait"])}
    for name in COLUMNS:
        mean, band = mean_band(point[name])
        row[name], row[f"{name}_band99"] = round(float(mean), 4), round(float(band), 4)
    row["beyond_gait"] = round(float(np.mean(point["mean_command"] > point["gait"])), 4)
    row["folder"] = point["folder"]
    return row


def paired(points: list[dict]) -> list[dict]:
    """The first start minus each other start, per body, at every epoch count both have (99 % t bands)."""
    first = points[0]["start"]
    mine = {p["epochs"]: p for p in points if p["start"] == first}
    rows = []
    for other in (p for p in points if p["start"] != first and p["epochs"] in mine):
        row = {"epochs": other["epochs"], "minus": other["start"], "of": first}
        for name in COLUMNS:
            mean, half = paired_band(mine[other["epochs"]][name] - other[name])
            row[name], row[f"{name}_band99"] = round(mean, 4), round(half, 4)
        rows.append(row)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    """Mean-command and stochastic moves against epochs, one line per start, with their bands."""
    from experiments.common import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), sharey=True)
    for ax, name in zip(axes, COLUMNS, strict=True):
        for start in dict.fromkeys(r["start"] for r in rows):
            mine = sorted((r for r in rows if r["start"] == start), key=lambda r: r["epochs"])
            x = [r["epochs"] for r in mine]
            y, band = np.array([r[name] for r in mine]), np.array([r[f"{name}_band99"] for r in mine])
            line, = ax.plot(x, y, "o-", label=f"from the {start}")
            ax.fill_between(x, y - band, y + band, color=line.get_color(), alpha=0.15)
        ax.set(xlabel="epochs of per-body training", title=name.replace("_", " "))
    axes[0].set_ylabel("move in 2 s (voxel lengths)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--from", dest="starts", nargs="+", action="append", required=True, metavar=("START", "POINT"),
                   help="a start's name, then its points EPOCHS=FOLDER (repeat --from for each start)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    points = []
    for start, *specs in args.starts:
        if not specs:
            p.error(f"--from {start}: give its points, EPOCHS=FOLDER")
        points += [read_point(start, s) for s in specs]
    for point in points[1:]:
        if point["keys"] != points[0]["keys"]:
            p.error(f"{point['folder']} holds other bodies than {points[0]['folder']}: compare on the same bodies")
    rows = [summary(pt) for pt in points]
    args.out.mkdir(parents=True, exist_ok=True)
    write_rows(args.out / "adaptation.csv", rows)
    pairs = paired(points)
    if pairs:
        write_rows(args.out / "paired.csv", pairs)
    plot(rows, args.out / "adaptation.png")
    for row in rows:
        print(f"{row['start']:>12} {row['epochs']:>3} epochs: {row['stochastic']:.3f} ± {row['stochastic_band99']:.3f}"
              f" / {row['mean_command']:.3f} ± {row['mean_command_band99']:.3f}, beyond gait {row['beyond_gait']:.0%}")
    for row in pairs:
        print(f"{row['of']} minus {row['minus']} at {row['epochs']} epochs: {row['stochastic']:+.3f} ± "
              f"{row['stochastic_band99']:.3f} / {row['mean_command']:+.3f} ± {row['mean_command_band99']:.3f}")


if __name__ == "__main__":
    main()
