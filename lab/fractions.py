"""Fractions of per-body control: any table's per-body figures against a reference's (``lab.reference``'s bodies.csv,
each body's own controller at a saved epoch), body by body, with 99 % bands (``freeform.tables.ratio_band``).

    python -m lab.fractions --reference lab/results/reference/design_unseen32 \\
        --table "student zero-shot=lab/results/fit93/trials_bodies.csv:trial_student" \\
        --table "fit, trials alone=lab/results/fit93/trials_bodies.csv" \\
        --table "fit, 24 epochs=lab/results/fit93/design_unseen32_adapt24_bodies.csv" --out DIR

A table is ``NAME=CSV[:COLUMN[:FIRST]]`` (``A.csv+B.csv``: several fits' tables as one, e.g. a set fitted in parts
whose ``body`` columns were numbered apart): its ``body`` column names the body (its row number where it has none),
COLUMN its figure (default ``mean_command``; ``A|B|…``: each body's best of those columns — a choice among
those candidates by their trials, from one fit's table), and its body FIRST + b is the reference's body b (default 0). Writes
``DIR/fractions.csv``: per table, the bodies, its mean, the reference's mean on them, the fraction and its band, and
the mean ``seconds`` a body where the table has them (``fit``'s).

A reference trained in parts (a bank of 8 bodies a session: ``lab/results/reference/grown_seed23/``) is
``--reference A+B+…``: their bodies in that order, each part at its own last saved epoch.

The fraction against seconds: ``--curve NAME=FIT_DIR[:FIRST]`` reads a ``fit --curve-every K`` folder's
``adaptation_bodies.csv`` (each body's move under what fit would keep if stopped at that point) and writes
``DIR/curve.csv`` (per curve and point: the epoch, a body's seconds, the fraction and its band) and ``DIR/curve.png``;
with several curves, ``DIR/paired.csv``: each later curve's move minus the first's at the epochs both measured, body by
body (voxel lengths, 99 % band by Student's t, the bodies ahead) — two recipes of the adaptation compared. With
``--pair-by point`` the k-th points of the curves are paired instead, whatever their epochs: recipes of equal compute
a point (``--copies 2`` measured every 8 epochs against ``--copies 4`` every 4) compared at equal seconds.

    python -m lab.fractions --reference lab/results/reference/design_unseen32 \
        --curve "fit=lab/results/fit93/design_unseen32_curve" --out DIR
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from freeform.tables import paired_band, ratio_band, read_rows, write_rows


def reference_moves(folder: Path, epoch: int | None = None) -> tuple[int | str, np.ndarray]:
    """``lab.reference``'s per-body moves ``[n]`` at ``epoch`` (None: the last saved) and that epoch. ``A+B``: a
    reference trained in parts (bodies 0 … of A, then B's, each bank until its own plateau), each at its own last
    saved epoch (or each at ``epoch``); the epoch is then the parts' joined by ``+``."""
    parts = str(folder).split("+")
    if len(parts) > 1:
        read = [reference_moves(Path(part), epoch) for part in parts]
        return "+".join(str(at) for at, _ in read), np.concatenate([moves for _, moves in read])
    rows = _read(folder / "bodies.csv", ("body",), "--reference", str(folder))
    epochs = sorted(int(k[len("epoch"):]) for k in rows[0] if k.startswith("epoch"))
    at = epochs[-1] if epoch is None else epoch
    if at not in epochs:
        raise ValueError(f"--epoch {epoch}: {folder} saved the epochs {epochs}")
    return at, np.array([float(r[f"epoch{at}"]) for r in rows])


def _first(text: str, flag: str, spec: str) -> int:
    try:
        return int(text or 0)
    except ValueError:
        raise ValueError(f"{flag} {spec!r}: FIRST must be a whole number, got {text!r}") from None


def _read(path: Path, columns: tuple[str, ...], flag: str, spec: str) -> list[dict[str, str]]:
    """``path``'s rows, which must exist and hold ``columns`` (the error names the flag and its value)."""
    if not Path(path).is_file():
        raise ValueError(f"{flag} {spec!r}: no file {path}")
    rows = read_rows(Path(path))
    if not rows:
        raise ValueError(f"{flag} {spec!r}: {path} has no rows")
    if missing := [c for c in columns if c not in rows[0]]:
        raise ValueError(f"{flag} {spec!r}: {path} has no column {missing[0]!r} (it has {list(rows[0])})")
    return rows


def per_body(rows: list[dict[str, str]], column: str, first: int, bodies: int) -> np.ndarray:
    """``column`` of ``rows`` as the reference's bodies ``[bodies]``: a row's ``body`` (its row number where there is
    none) less ``first`` is the reference's body; one the rows lack is NaN (left out of a fraction)."""
    out = np.full(bodies, np.nan)
    for i, row in enumerate(rows):
        if 0 <= (b := int(row.get("body", i)) - first) < bodies:
            out[b] = float(row[column])
    return out


def table_moves(spec: str, bodies: int) -> tuple[str, np.ndarray, np.ndarray]:
    """``NAME=CSV[:COLUMN[:FIRST]]`` (module docstring) → (name, figures ``[bodies]``, seconds ``[bodies]``, NaN
    where the table has none)."""
    name, sep, rest = spec.partition("=")
    if not sep:
        raise ValueError(f"--table {spec!r}: give NAME=CSV[:COLUMN[:FIRST]]")
    paths, _, rest = rest.partition(":")
    column, _, first = rest.partition(":")
    columns = tuple((column or "mean_command").split("|"))
    rows = [row for path in paths.split("+") for row in _read(Path(path), columns, "--table", spec)]
    at = _first(first, "--table", spec)
    seconds = per_body(rows, "seconds", at, bodies) if "seconds" in rows[0] else np.full(bodies, np.nan)
    return name, np.fmax.reduce([per_body(rows, c, at, bodies) for c in columns]), seconds  # (NaN: not that one)


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


def curve_points(reference: Path, curves: list[str], epoch: int | None = None,
                 by: str = "epoch") -> tuple[list[dict], list[dict]]:
    """The fraction of per-body control against a body's seconds, a row per ``--curve`` (module docstring) and point;
    and each later curve against the first, paired by body, a row per epoch both measured (``by`` "point": a row
    per point both have, the k-th with the k-th)."""
    at, ref = reference_moves(reference, epoch)
    if len(names := [spec.partition("=")[0] for spec in curves]) > len(set(names)):
        raise ValueError(f"--curve: two curves share a name ({names}): give each its own")
    rows, moves = [], {}
    for spec in curves:
        name, sep, rest = spec.partition("=")
        if not sep:
            raise ValueError(f"--curve {spec!r}: give NAME=FIT_DIR[:FIRST], a folder of fit --curve-every K")
        folder, _, first = rest.partition(":")
        points = _read(Path(folder) / "adaptation_bodies.csv", ("epoch", "seconds", "body", "kept"), "--curve", spec)
        start = _first(first, "--curve", spec)
        for e in sorted({int(p["epoch"]) for p in points}):
            mine = [p for p in points if int(p["epoch"]) == e]
            kept = per_body(mine, "kept", start, len(ref))
            if not np.isfinite(kept).any():
                raise ValueError(f"--curve {spec!r}: at epoch {e} none of its bodies is one of the reference's "
                                 f"{len(ref)} (check FIRST)")
            fraction, band = ratio_band(kept, ref)
            moves[name, e] = kept
            seconds = float(np.mean([float(p["seconds"]) for p in mine]))  # (bodies fitted in parts: each its own)
            rows.append({"curve": name, "epoch": e, "seconds_a_body": seconds, "bodies": int(np.isfinite(kept).sum()),
                         "reference_epoch": at, "fraction": fraction, "band99": band})
            print(f"{name}, epoch {e} ({seconds:.1f} s a body): {fraction:.1%} ± {band:.1%}")
    return rows, paired_curves(moves, by)


def paired_curves(moves: dict[tuple[str, int], np.ndarray], by: str = "epoch") -> list[dict]:
    """Each later curve's moves ``[bodies]`` minus the first curve's at every epoch both measured (``by`` "point":
    the k-th point of each, whatever its epoch; bodies either lacks left out): the mean difference, its 99 % band,
    and the bodies ahead, beside the two epochs paired."""
    if by not in ("epoch", "point"):
        raise ValueError(f"--pair-by {by!r}: epoch or point")
    names = list(dict.fromkeys(name for name, _ in moves))
    epochs = {n: [e for other, e in moves if other == n] for n in names}  # (in the order measured: ascending)
    rows = []
    for name in names[1:]:
        if by == "point" and len(epochs[name]) != len(epochs[names[0]]):
            print(f"--pair-by point: {name} has {len(epochs[name])} points, {names[0]} {len(epochs[names[0]])}: the "
                  "first of each paired, the rest left out")
        pairs = (zip(epochs[name], epochs[names[0]], strict=False) if by == "point"
                 else [(e, e) for e in epochs[name] if e in epochs[names[0]]])
        for e, against in pairs:
            d = moves[name, e] - moves[names[0], against]
            if not np.isfinite(d).any():
                raise ValueError(f"--curve {name} and {names[0]}: at epochs {e} and {against} they share no body")
            d = d[np.isfinite(d)]
            mean, band = paired_band(d)
            rows.append({"curve": name, "against": names[0], "epoch": e, "against_epoch": against, "bodies": len(d),
                         "difference": mean, "band99": band, "ahead": int((d > 0).sum())})
            print(f"{name} (epoch {e}) - {names[0]} (epoch {against}): {mean:+.3f} ± {band:.3f} "
                  f"({int((d > 0).sum())} of {len(d)} ahead)")
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
    ax.set_xlabel("seconds a body (the host that ran fit)")
    ax.set_ylabel(f"% of per-body control (epoch {rows[0]['reference_epoch']})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference", type=Path, required=True,
                   help="a lab.reference output folder (A+B: a reference trained in parts, bodies in that order)")
    p.add_argument("--epoch", type=int, default=None, help="the reference's saved epoch (default: its last)")
    p.add_argument("--table", action="append", default=[], metavar="NAME=CSV[:COLUMN[:FIRST]]")
    p.add_argument("--curve", action="append", default=[], metavar="NAME=FIT_DIR[:FIRST]")
    p.add_argument("--pair-by", choices=("epoch", "point"), default="epoch",
                   help="pair the curves by epoch, or by point (the k-th of each: equal compute a point)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if not args.table and not args.curve:
        p.error("give at least one --table or --curve")
    if (args.out / "fractions.csv").exists() or (args.out / "curve.csv").exists():
        p.error(f"--out {args.out} holds fractions.csv or curve.csv already: give a new folder (nothing is "
                "overwritten)")
    try:  # (everything is read before anything is written)
        table_rows = fractions(args.reference, args.table, args.epoch) if args.table else []
        curve_rows, paired_rows = (curve_points(args.reference, args.curve, args.epoch, args.pair_by) if args.curve
                                   else ([], []))
    except ValueError as exc:
        p.error(str(exc))
    if table_rows:
        write_rows(args.out / "fractions.csv", table_rows)
    if curve_rows:
        write_rows(args.out / "curve.csv", curve_rows)
        draw_curves(curve_rows, args.out / "curve.png")
    if paired_rows:
        write_rows(args.out / "paired.csv", paired_rows)


if __name__ == "__main__":
    main()
