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
``--firsts 8,16``: the zoo and the library's first K members (the table's order: the library as it was before it
grew), and what the rest add to them (paired, 99 %) — a library's growth measured within one run's trials.

``--figures TEMPLATE`` (steering): a body's move under its pick is not its trial — the trials are other episodes'
headings than the figures', so that no figure is measured on the draw that chose it — but the pick's
``mean_command`` in ``TEMPLATE.format(name=<candidate>)``, an ``evaluate --episodes K`` bodies.csv of that candidate
on the table's bodies (``fit --headings random``'s figures: each body's row draws)::

    freeform-control fit du0.npy --headings random --adapt-epochs 0 --out DIR --candidates ZOO... LIB/l0/controller.pt ...
    freeform-control evaluate student_steering du0.npy --episodes 4 --out E/student_steering     # each candidate
    python -m lab.library DIR/bodies.csv --library l --own --figures 'E/{name}/bodies.csv' --reference REF

(a prefix must name no zoo candidate: ``s`` would also take ``student_steering``; the library's members are printed)
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
        if len(library) != len(rows) or len(rows) < 2:
            # (one more or fewer shifts every own: a prefix that also names a zoo candidate, e.g. "s" and
            # student_steering, would leave each body its own controller under another's name)
            raise ValueError(f"--own: {len(rows)} bodies and {len(library)} library controllers ({', '.join(library)}):"
                             " body i's own is the library's i-th, so the library needs one for every body and no "
                             "more (and two at least)")
        lib[np.arange(len(rows)), np.arange(len(rows))] = -np.inf
    return z, lib


def figures(rows: list[dict[str, str]], prefix: str, template: str) -> tuple[np.ndarray, np.ndarray]:
    """Each body's figure under each zoo candidate ``[M, Z]`` and library candidate ``[M, L]``: the ``mean_command``
    column of ``template.format(name=<candidate>)`` (an ``evaluate`` bodies.csv of the table's bodies, in order)."""
    if "{name}" not in template:
        raise ValueError(f"--figures {template!r}: the template must hold {{name}} (each candidate's name)")
    zoo, library = trial_columns(rows, prefix)
    bodies = [r["body"] for r in rows]
    columns = []
    for name in zoo + library:
        try:
            path = Path(template.format(name=name))
        except (KeyError, IndexError, ValueError):
            raise ValueError(f"--figures {template!r}: the only field it may hold is {{name}}") from None
        if not path.is_file():
            raise ValueError(f"--figures: no {path} for the candidate {name!r} (evaluate it on the table's bodies)")
        figure = read_rows(path)
        if [r["body"] for r in figure] != bodies:
            raise ValueError(f"--figures: {path}'s bodies are not the table's ({len(figure)} rows against "
                             f"{len(bodies)}, or in another order): evaluate the candidate on the table's bodies")
        columns.append([float(r["mean_command"]) for r in figure])
    table = np.array(columns).T
    return table[:, : len(zoo)], table[:, len(zoo):]


def choices(rows: list[dict[str, str]], prefix: str, own: bool,
            scored: tuple[np.ndarray, np.ndarray] | None = None, members: int | None = None) -> dict[str, np.ndarray]:
    """Each body's move ``[M]`` under its best whole-episode trial over the zoo, the library and both
    (:func:`trials`; a tie to the zoo): the trial itself, or the pick's figure in ``scored`` (:func:`figures`).
    ``members``: the library's first that many (in the table's order) stand for it — what it was before it grew."""
    z, lib = trials(rows, prefix, own)
    fz, flib = (z, lib) if scored is None else scored
    if members is not None:
        if not 0 < members < lib.shape[1]:
            raise ValueError(f"--firsts {members}: the library's first K members, 0 < K < its {lib.shape[1]}")
        lib, flib = lib[:, :members], flib[:, :members]
    body = np.arange(len(rows))
    zoo, library = fz[body, z.argmax(1)], flib[body, lib.argmax(1)]
    return {"zoo": zoo, "library": library, "zoo and library": np.where(lib.max(1) > z.max(1), library, zoo)}


def expected_best(floor: np.ndarray, library: np.ndarray, size: int, floor_figure: np.ndarray | None = None,
                  library_figure: np.ndarray | None = None) -> np.ndarray:
    """Each body's expected move ``[M]`` under the best trial of ``floor`` ``[M]`` (its best zoo trial) and ``size``
    library controllers drawn at random without replacement from its row of ``library`` ``[M, L]`` (``-inf``: not
    drawable, a body's own); the move is the pick's trial, or its figure (``floor_figure`` ``[M]``,
    ``library_figure`` ``[M, L]``). Exact: the draw's best is the row's j-th by trial with probability
    C(n − j, size − 1) / C(n, size)."""
    if size < 1:
        raise ValueError(f"a library size must be at least 1, got {size}")
    floor_figure = floor if floor_figure is None else floor_figure
    library_figure = library if library_figure is None else library_figure
    out = np.empty(len(floor))
    for i, (z, row) in enumerate(zip(floor, library, strict=True)):
        order = np.argsort(-row, kind="stable")[: int(np.isfinite(row).sum())]
        n = len(order)
        if size > n:
            raise ValueError(f"library size {size}: body {i} can draw from {n} controllers only (its own left out): "
                             f"give --sizes of at most {n}")
        j = np.arange(1, n + 1)
        p = comb(n - j, size - 1) / comb(n, size)
        out[i] = float((p * np.where(row[order] > z, library_figure[i, order], floor_figure[i])).sum())
    return out


FIRSTS = "zoo and the library's first "
"""The name of :func:`choices`' ``members`` rows (``--firsts``): ``FIRSTS + K``."""


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
        if name.startswith(FIRSTS):  # (what the rest of the library adds to its first K)
            row["whole_over_it"], row["whole_band99"] = paired_band(best["zoo and library"] - moves)
            row["bodies_gaining_whole"] = int((best["zoo and library"] > moves).sum())
        rows.append(row)
    return rows


def whole_numbers(option: str, text: str) -> list[int]:
    """``option``'s comma-separated whole numbers (``"1,4,16"``); empty: none."""
    try:
        return [int(k) for k in text.split(",") if k.strip()]
    except ValueError:
        raise ValueError(f"{option} {text!r}: give whole numbers separated by commas, e.g. 1,4,16") from None


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
    p.add_argument("--figures", default=None, metavar="TEMPLATE",
                   help="each candidate's evaluate bodies.csv, '{name}' standing for it: a pick's move is its figure")
    p.add_argument("--firsts", default="", metavar="K,K,...",
                   help="also the zoo and the library's first K members (the table's order), and what the rest add")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    try:
        rows = read_rows(args.table)
        scored = None if args.figures is None else figures(rows, args.library, args.figures)
        best = choices(rows, args.library, args.own, scored)
        z, library = trials(rows, args.library, args.own)
        sizes, firsts = whole_numbers("--sizes", args.sizes), whole_numbers("--firsts", args.firsts)
        for k in firsts:
            best[f"{FIRSTS}{k}"] = choices(rows, args.library, args.own, scored, members=k)["zoo and library"]
        # (scored by figures, the zoo's floor is its pick's figure and each member's its own)
        floor_figure, library_figure = (best["zoo"], scored[1]) if scored is not None else (None, None)
        for k in sizes:
            best[f"zoo and {k} of the library"] = expected_best(z.max(1), library, k, floor_figure, library_figure)
        at, ref = reference_moves(args.reference, args.epoch) if args.reference else (None, None)
        if ref is not None and len(ref) != len(rows):
            raise ValueError(f"--reference {args.reference}: {len(ref)} bodies, the table {len(rows)}")
    except ValueError as exc:
        p.error(str(exc))
    out = summary(best, ref)
    members = trial_columns(rows, args.library)[1]  # (a prefix that also names a zoo candidate shows here)
    print(f"the library ({len(members)}, --library {args.library!r}): {', '.join(members)}")
    for row in out:
        text = f"{row['choice']}: {row['mean']:.3f}"
        if "fraction" in row:
            text += f", {row['fraction']:.1%} ± {row['band99']:.1%} of per-body control at epoch {at}"
        if "gain_over_zoo" in row:
            text += (f"; over the zoo {row['gain_over_zoo']:+.3f} ± {row['gain_band99']:.3f} "
                     f"({row['bodies_gaining']} of {row['bodies']} bodies)")
        if "whole_over_it" in row:
            text += (f"; the whole library over it {row['whole_over_it']:+.3f} ± {row['whole_band99']:.3f} "
                     f"({row['bodies_gaining_whole']} bodies gain)")
        print(text)
    if args.out:
        write_rows(args.out, out)


if __name__ == "__main__":
    main()
