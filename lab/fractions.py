"""Fractions of per-body control: any table's per-body figures against a reference's (``lab.reference``'s bodies.csv,
each body's own controller at a saved epoch), body by body, with 99 % bands (``freeform.tables.ratio_band``).

    python -m lab.fractions --reference lab/results/reference/design_unseen32 \\
        --table "student zero-shot=lab/results/fit93/trials_bodies.csv:trial_student" \\
        --table "fit, trials alone=lab/results/fit93/trials_bodies.csv" \\
        --table "fit, 24 epochs=lab/results/fit93/design_unseen32_adapt24_bodies.csv" --out DIR

A table is ``NAME=CSV[:COLUMN[:FIRST]]``: its ``body`` column names the body (its row number where it has none),
COLUMN its figure (default ``mean_command``), and its body FIRST + b is the reference's body b (default 0). Writes
``DIR/fractions.csv``: per table, the bodies, its mean, the reference's mean on them, the fraction and its band, and
the mean ``seconds`` a body where the table has them (``fit``'s).

The fraction against seconds: ``--curve NAME=FIT_DIR[:FIRST]`` reads a ``fit --curve-every K`` folder's
``adaptation_bodies.csv`` (each body's move under what fit would keep if stopped at that point) and writes
``DIR/curve.csv`` (per curve and point: the epoch, a body's seconds, the fraction and its band) and ``DIR/curve.png``.

    python -m lab.fractions --reference lab/results/reference/design_unseen32 \
        --curve "fit=lab/results/fit93/design_unseen32_curve" --out DIR
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from freeform.tables import ratio_band, write_rows


def reference_moves(folder: Path, epoch: int | None = None) -> tuple[int, np.ndarray]:
    """``lab.reference``'s per-body moves ``[n]`` at ``epoch`` (None: the last saved) and that epoch."""
    with open(folder / "bodies.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    epochs = sorted(int(k[len("epoch"):]) for k in rows[0] if k.startswith("epoch"))
    at = epochs[-1] if epoch is None else epoch
    if at not in epochs:
        raise ValueError(f"--epoch {epoch}: {folder} saved the epochs {epochs}")
    return at, np.array([float(r[f"epoch{at}"]) for r in rows])


def table_moves(spec: str, bodies: int) -> tuple[str, np.ndarray, np.ndarray]:
    """``NAME=CSV[:COLUMN[:FIRST]]`` (module docstring) → (name, figures ``[bodies]``, seconds ``[bodies]`` or
    empty); a reference body the table lacks is NaN (left out of the fraction)."""
    name, sep, rest = spec.partition("=")
    if not sep:
        raise ValueError(f"--table {spec!r}: give NAME=CSV[:COLUMN[:FIRST]]")
    parts = rest.split(":")
    path, column, first = parts[0], parts[1] if len(parts) > 1 else "mean_command", int(parts[2]) if len(parts) > 2 else 0
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or column not in rows[0]:
        raise ValueError(f"--table {name}: {path} has no column {column!r} (it has {list(rows[0]) if rows else []})")
    figures, seconds = np.full(bodies, np.nan), np.full(bodies, np.nan)
    for i, row in enumerate(rows):
        b = int(row.get("body", i)) - first
        if 0 <= b < bodies:
            figures[b] = float(row[column])
            seconds[b] = float(row["seconds"]) if "seconds" in row else np.nan
    return name, figures, seconds


def fractions(reference: Path, tables: list[str], epoch: int | None = None) -> list[dict]:
    at, ref = reference_moves(reference, epoch)
    rows = []
    for spec in tables:
        name, figures, seconds = table_moves(spec, len(ref))
        both = np.isfinite(figures)
        fraction, band = ratio_band(figures, ref)
        rows.append({"table": name, "bodies": int(both.sum()), "mean": float(figures[both].mean()),
                     "reference": float(ref[both].mean()), "reference_epoch": at, "fraction": fraction,
                     "band99": band, "seconds_a_body": float(np.nanmean(seconds)) if np.isfinite(seconds).any()
                     else float("nan")})
        print(f"{name}: {fraction:.1%} ± {band:.1%} of per-body control at epoch {at} ({int(both.sum())} bodies)")
    return rows


def curve_points(reference: Path, curves: list[str], epoch: int | None = None) -> list[dict]:
    """The fraction of per-body control against a body's seconds, a row per ``--curve`` (module docstring) and point."""
    at, ref = reference_moves(reference, epoch)
    rows = []
    for spec in curves:
        name, sep, rest = spec.partition("=")
        folder, _, first = rest.partition(":")
        path = Path(folder) / "adaptation_bodies.csv"
        if not sep or not path.is_file():
            raise ValueError(f"--curve {spec!r}: give NAME=FIT_DIR[:FIRST], a folder of fit --curve-every K "
                             f"(no {path})")
        with open(path, newline="") as f:
            points = list(csv.DictReader(f))
        for e in sorted({int(p["epoch"]) for p in points}):
            kept = np.full(len(ref), np.nan)
            mine = [p for p in points if int(p["epoch"]) == e]
            for p in mine:
                if 0 <= (b := int(p["body"]) - int(first or 0)) < len(ref):
                    kept[b] = float(p["kept"])
            fraction, band = ratio_band(kept, ref)
            rows.append({"curve": name, "epoch": e, "seconds_a_body": float(mine[0]["seconds"]),
                         "bodies": int(np.isfinite(kept).sum()), "reference_epoch": at, "fraction": fraction,
                         "band99": band})
            print(f"{name}, epoch {e} ({float(mine[0]['seconds']):.1f} s a body): {fraction:.1%} ± {band:.1%}")
    return rows


def draw_curves(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name in dict.fromkeys(r["curve"] for r in rows):
        mine = [r for r in rows if r["curve"] == name]
        x = [r["seconds_a_body"] for r in mine]
        y = np.array([r["fraction"] for r in mine]) * 100
        band = np.array([r["band99"] for r in mine]) * 100
        ax.plot(x, y, marker="o", label=name)
        ax.fill_between(x, y - band, y + band, alpha=0.2)
    ax.axhline(100, color="grey", lw=0.8)
    ax.set_xlabel("seconds a body (2-core host)")
    ax.set_ylabel(f"% of per-body control (epoch {rows[0]['reference_epoch']})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference", type=Path, required=True, help="a lab.reference output folder")
    p.add_argument("--epoch", type=int, default=None, help="the reference's saved epoch (default: its last)")
    p.add_argument("--table", action="append", default=[], metavar="NAME=CSV[:COLUMN[:FIRST]]")
    p.add_argument("--curve", action="append", default=[], metavar="NAME=FIT_DIR[:FIRST]")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if not args.table and not args.curve:
        p.error("give at least one --table or --curve")
    if (args.out / "fractions.csv").exists() or (args.out / "curve.csv").exists():
        p.error(f"--out {args.out} holds fractions already: give a new folder (nothing is overwritten)")
    try:  # (everything is read before anything is written)
        table_rows = fractions(args.reference, args.table, args.epoch) if args.table else []
        curve_rows = curve_points(args.reference, args.curve, args.epoch) if args.curve else []
    except ValueError as exc:
        p.error(str(exc))
    if table_rows:
        write_rows(args.out / "fractions.csv", table_rows)
    if curve_rows:
        write_rows(args.out / "curve.csv", curve_rows)
        draw_curves(curve_rows, args.out / "curve.png")


if __name__ == "__main__":
    main()
