"""A library of per-body controllers as ``fit``'s candidates: each body's best trial over the zoo alone, over the
library, and over both — with the body's own controller left out where the library holds it (leave-one-out: the
library's controllers were trained on bodies of the same table, and a body must not be scored by its own).

    freeform-control fit BODIES.npy --out DIR --adapt-epochs 0 --candidates ZOO... LIB/t00/controller.pt ...
    python -m lab.library DIR/bodies.csv --library t --own --reference lab/results/reference/design_unseen32

``--library PREFIX``: the candidates whose names start with PREFIX are the library's (``t00`` … from ``LIB/t00/``),
the rest the zoo's. ``--own``: the table's body i was the library's i-th controller's own (left out of its choice).
``--reference``: a ``lab.reference`` folder, for the fraction of per-body control (its bodies must be the table's).
Prints each choice's mean move, its fraction of the reference (99 % band, paired by body), and the library's gain
over the zoo alone (paired, 99 %); ``--out CSV`` writes those rows. ``--sizes 1,4,16``: the same for a library of
that many controllers drawn at random from it — each body's expected best over every such draw, exactly (no
sampling): what a smaller library of the same kind would give, and so what each candidate's trial second buys.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.special import comb

from freeform.tables import paired_band, ratio_band, read_rows, write_rows


def trial_columns(rows: list[dict[str, str]], prefix: str) -> tuple[list[str], list[str]]:
    """The table's zoo and library candidates (``trial_<name>`` columns), the library's those named ``prefix``…"""
    names = [k[len("trial_"):] for k in rows[0] if k.startswith("trial_")]
    library = [n for n in names if n.startswith(prefix)]
    if not library or len(library) == len(names):
        raise ValueError(f"--library {prefix!r}: the candidates are {names}; the prefix must name some, not all")
    return [n for n in names if n not in library], library


def trials(rows: list[dict[str, str]], prefix: str, own: bool) -> tuple[np.ndarray, np.ndarray]:
    """Each body's whole-episode trials of the zoo ``[M, Z]`` and of the library ``[M, L]``; with ``own``, body i's
    trial of the library's i-th controller is ``-inf`` (never chosen)."""
    zoo, library = trial_columns(rows, prefix)
    z = np.array([[float(r[f"trial_{n}"]) for n in zoo] for r in rows])
    lib = np.array([[float(r[f"trial_{n}"]) for n in library] for r in rows])
    if own:
        if len(library) < max(len(rows), 2):
            raise ValueError(f"--own: {len(rows)} bodies and {len(library)} library controllers: body i's own is "
                             "the library's i-th, so the library needs one for every body (and two at least)")
        lib[np.arange(len(rows)), np.arange(len(rows))] = -np.inf
    return z, lib


def choices(rows: list[dict[str, str]], prefix: str, own: bool) -> dict[str, np.ndarray]:
    """Each body's best whole-episode trial ``[M]`` over the zoo, the library and both (:func:`trials`)."""
    z, lib = trials(rows, prefix, own)
    return {"zoo": z.max(1), "library": lib.max(1), "zoo and library": np.maximum(z.max(1), lib.max(1))}


def expected_best(floor: np.ndarray, library: np.ndarray, size: int) -> np.ndarray:
    """Each body's expected best ``[M]`` of ``floor`` ``[M]`` (its best zoo trial) and ``size`` library controllers
    drawn at random without replacement from its row of ``library`` ``[M, L]`` (``-inf``: not drawable, a body's
    own). Exact: the draw's best is the row's j-th largest with probability C(n − j, size − 1) / C(n, size)."""
    if size < 1:
        raise ValueError(f"a library size must be at least 1, got {size}")
    out = np.empty(len(floor))
    for i, (z, row) in enumerate(zip(floor, library, strict=True)):
        values = np.sort(row[np.isfinite(row)])[::-1]
        n = len(values)
        if size > n:
            raise ValueError(f"library size {size}: body {i} can draw from {n} controllers only (its own left out): "
                             f"give --sizes of at most {n}")
        j = np.arange(1, n + 1)
        p = comb(n - j, size - 1) / comb(n, size)
        out[i] = float((p * np.maximum(z, values)).sum())
    return out


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
    p.add_argument("--sizes", default="", metavar="K,K,...",
                   help="also a random library of each size K (each body's exact expected best over the draws)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    try:
        rows = read_rows(args.table)
        best = choices(rows, args.library, args.own)
        library = trials(rows, args.library, args.own)[1]
        try:
            sizes = [int(k) for k in args.sizes.split(",") if k.strip()]
        except ValueError:
            raise ValueError(f"--sizes {args.sizes!r}: give whole numbers separated by commas, e.g. 1,4,16") from None
        for k in sizes:
            best[f"zoo and {k} of the library"] = expected_best(best["zoo"], library, k)
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
