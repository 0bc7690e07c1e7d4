"""A library of per-body controllers as ``fit``'s candidates: each body's best trial over the zoo alone, over the
library, and over both — with the body's own controller left out where the library holds it (leave-one-out: the
library's controllers were trained on bodies of the same table, and a body must not be scored by its own).

    freeform-control fit BODIES.npy --out DIR --adapt-epochs 0 --candidates ZOO... LIB/t00/controller.pt ...
    python -m lab.library DIR/bodies.csv --library t --own --reference lab/results/reference/design_unseen32

``--library PREFIX``: the candidates whose names start with PREFIX are the library's (``t00`` … from ``LIB/t00/``),
the rest the zoo's. ``--own``: the table's body i was the library's i-th controller's own (left out of its choice).
``--reference``: a ``lab.reference`` folder, for the fraction of per-body control (its bodies must be the table's).
Prints each choice's mean move, its fraction of the reference (99 % band, paired by body), and the library's gain
over the zoo alone (paired, 99 %); ``--out CSV`` writes those rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from freeform.tables import paired_band, ratio_band, read_rows, write_rows


def trial_columns(rows: list[dict[str, str]], prefix: str) -> tuple[list[str], list[str]]:
    """The table's zoo and library candidates (``trial_<name>`` columns), the library's those named ``prefix``…"""
    names = [k[len("trial_"):] for k in rows[0] if k.startswith("trial_")]
    library = [n for n in names if n.startswith(prefix)]
    if not library or len(library) == len(names):
        raise ValueError(f"--library {prefix!r}: the candidates are {names}; the prefix must name some, not all")
    return [n for n in names if n not in library], library


def choices(rows: list[dict[str, str]], prefix: str, own: bool) -> dict[str, np.ndarray]:
    """Each body's best whole-episode trial ``[M]`` over the zoo, the library and both; with ``own``, body i's
    choice leaves out the library's i-th controller."""
    zoo, library = trial_columns(rows, prefix)
    z = np.array([[float(r[f"trial_{n}"]) for n in zoo] for r in rows])
    lib = np.array([[float(r[f"trial_{n}"]) for n in library] for r in rows])
    if own:
        if len(library) < max(len(rows), 2):
            raise ValueError(f"--own: {len(rows)} bodies and {len(library)} library controllers: body i's own is "
                             "the library's i-th, so the library needs one for every body (and two at least)")
        lib[np.arange(len(rows)), np.arange(len(rows))] = -np.inf
    return {"zoo": z.max(1), "library": lib.max(1), "zoo and library": np.maximum(z.max(1), lib.max(1))}


def summary(best: dict[str, np.ndarray], reference: np.ndarray | None = None) -> list[dict]:
    """A row per choice of :func:`choices`: its bodies' mean move, its fraction of ``reference`` ``[M]`` (each body's
    per-body control; 99 % band, paired by body) where given, and its gain over the zoo alone (paired, 99 %)."""
    rows = []
    for name, moves in best.items():
        row = {"choice": name, "bodies": len(moves), "mean": float(moves.mean())}
        if reference is not None:
            row["fraction"], row["band99"] = ratio_band(moves, reference)
        if name != "zoo":
            row["gain_over_zoo"], row["gain_band99"] = paired_band(moves - best["zoo"])
            row["bodies_gaining"] = int((moves > best["zoo"]).sum())
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    from lab.fractions import reference_moves

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("table", type=Path, help="a fit --adapt-epochs 0 bodies.csv")
    p.add_argument("--library", required=True, metavar="PREFIX")
    p.add_argument("--own", action="store_true")
    p.add_argument("--reference", type=Path, default=None)
    p.add_argument("--epoch", type=int, default=None, help="the reference's saved epoch (default: its last)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    try:
        rows = read_rows(args.table)
        best = choices(rows, args.library, args.own)
        at, ref = reference_moves(args.reference, args.epoch) if args.reference else (None, None)
        if ref is not None and len(ref) != len(rows):
            raise ValueError(f"--reference {args.reference}: {len(ref)} bodies, the table {len(rows)}")
    except ValueError as exc:
        p.error(str(exc))
    out = summary(best, ref)
    for row in out:
        text = f"{row['choice']}: {row['mean']:.3f}"
        if "fraction" in row:
            text += f", {row['fraction']:.1%} ± {row['band99']:.1%} of per-body control at epoch {at}"
        if "gain_over_zoo" in row:
            text += (f"; over the zoo {row['gain_over_zoo']:+.3f} ± {row['gain_band99']:.3f} "
                     f"({row['bodies_gaining']} of {row['bodies']} bodies)")
        print(text)
    if args.out:
        write_rows(args.out, out)


if __name__ == "__main__":
    main()
