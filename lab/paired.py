"""Two held-out tables compared body by body: each controller's move on a body minus the other's on the same body
(same headings, same noise streams: the across-body spread cancels), with a 99 % band over the bodies (Student's
t, :func:`experiments.common.paired_band`). Every "paired" figure of ``docs/control.md`` is this command's::

    python -m lab.paired runs/eval_gen4_93 lab/results/control_student/heldout93/student64_gen3_bodies.csv

A and B are output folders of ``python -m lab.control --evaluate ... --bodies`` or of ``python -m
lab.heldout --pool`` (their ``bodies.csv``), or such a table as the results keep it
(``heldout93/<name>_bodies.csv``). They must hold the same bodies in the same order under the same episode
settings: each body's set, index and open-loop gait are checked (to the bit on one host; across hosts within
``HOST_DRIFT``, warned). Prints, per column (stochastic, mean command),
A's and B's means, A − B with its band and the fraction of bodies on which A moves further; ``--out CSV`` writes
the same rows.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

from experiments.common import paired_band, read_rows, write_rows

COLUMNS = {"stochastic": "controller", "mean command": "mean_command"}
"""What is compared -> the ``bodies.csv`` column it is read from."""
HOST_DRIFT = {"atol": 0.05, "rtol": 0.05, "median": 0.005}
"""How far the same body's own gait may move between hosts (voxel lengths): the production step's fast-math
floating point differs with the CPU it was compiled for, and a 2 s episode of contacts carries a last-bit change
to the fourth digit — median |Δ| 9e-5, largest 0.035 over the 93 held-out bodies between two AVX-512 hosts
(2026-12-01) — while another body, or other episode settings, moves it by tenths (median 0.28). Two tables
of one set taken on two hosts are kept within ``atol + rtol·|gait|`` for every body and ``median`` over the set."""


def same_gait(a: float, b: float) -> bool:
    """Whether two tables' figures for one body's own gait can be the same body under the same episode settings:
    equal, or within :data:`HOST_DRIFT` of each other."""
    return bool(np.isclose(a, b, rtol=HOST_DRIFT["rtol"], atol=HOST_DRIFT["atol"]))


def check_drift(gaits_a: list[float], gaits_b: list[float], where: str) -> str | None:
    """One set's own-gait figures in two tables, after every body passed :func:`same_gait`: a set moved as a whole
    (the median |Δ| beyond :data:`HOST_DRIFT`'s) is other episode settings, refused naming ``where``; a set moved
    at all was evaluated on another host, which is returned in words (None where every figure is equal) for the
    caller to warn about once (:func:`warn_hosts`)."""
    drift = np.abs(np.asarray(gaits_a, dtype=float) - np.asarray(gaits_b, dtype=float))
    median = float(np.median(drift)) if drift.size else 0.0
    if median > HOST_DRIFT["median"]:
        raise ValueError(f"{where}: the bodies walked their own gaits a median {median:.4f} apart (the same bodies on "
                         f"another host: < {HOST_DRIFT['median']}): other episode settings (evaluate with the same "
                         "--headings, --eval-episodes and seed)")
    if not (drift.size and drift.max() > 0.0):  # (one host: the same bits, so the same figures to the digit)
        return None
    return (f"{where}: the bodies walked their own gaits within the floating point of another host (median |Δ| "
            f"{median:.1e}, largest {drift.max():.1e} voxel lengths)")


def warn_hosts(drifts: list[str]) -> None:
    """One warning for every set of :func:`check_drift`'s that was measured on another host (none: no warning)."""
    if drifts:
        warnings.warn(f"{len(drifts)} table-and-set pairs of these tables were measured on two hosts (their bodies' "
                      f"own gaits within floating point of each other), the first: {drifts[0]}", stacklevel=3)


def read_table(source: Path, who: str, made_by: str) -> list[dict[str, str]]:
    """A held-out table's rows: ``source`` is its ``bodies.csv`` (any ``.csv``) or the folder holding one; refused
    naming ``who`` asked and what writes one (``made_by``)."""
    path = source if source.suffix == ".csv" else source / "bodies.csv"
    if not path.is_file():
        raise ValueError(f"{who}: no {path.name} there (give an output folder of {made_by})")
    return read_rows(path)


def table_run(source: Path) -> dict:
    """A held-out table's ``run.json``, found as :func:`read_table` finds its rows: beside the folder's
    ``bodies.csv``, or ``<name>_run.json`` beside ``<name>_bodies.csv`` as the results keep a table; {} where
    there is none."""
    path = source.with_name(source.name.removesuffix("bodies.csv") + "run.json") if source.suffix == ".csv" else \
        source / "run.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def set_files(source: Path) -> dict[str, str]:
    """A pooled table's set folders -> the file name of each set's bodies, from the ``run.json`` that
    ``lab.heldout --pool`` writes (:func:`table_run`); empty where it records none (tables pooled before it
    recorded its sets)."""
    run = table_run(source)
    folders, sets = run.get("pooled") or [], run.get("sets") or []
    if len(folders) != len(sets) or not all(isinstance(e, dict) and e.get("bodies") for e in sets):
        return {}
    return {str(folder): Path(str(entry["bodies"])).name for folder, entry in zip(folders, sets, strict=True)}


def body_keys(rows: list[dict[str, str]], sets: dict[str, str] | None = None) -> list[tuple[str, str]]:
    """Each row's body: its set and its index. A pooled table's set is its bodies' file (``sets``: the set folder
    -> that file, :func:`set_files`) or, where either table does not record it, the set folder's last ``_`` part
    (``eval_x_grown`` -> ``grown``); none in a single set's table."""
    if sets:
        return [(sets[r["set"]], r["body"]) for r in rows]
    return [(r.get("set", "").rsplit("_", 1)[-1], r["body"]) for r in rows]


def same_bodies(a: list[dict[str, str]], b: list[dict[str, str]], name_a: str, name_b: str,
                sets: tuple[dict[str, str], dict[str, str]] = ({}, {})) -> list[str]:
    """Refuse, naming the first body that differs, tables of other bodies or other episode settings (the same body
    under the same settings walks its own gait the same); returns the sets measured on two hosts, in words
    (:func:`check_drift`). ``sets``: each table's :func:`set_files`, used where both
    record the sets of all their rows (two folders of one set file then match whatever their names)."""
    if len(a) != len(b):
        raise ValueError(f"{name_a} holds {len(a)} bodies and {name_b} {len(b)}: compare tables of the same bodies")
    both = all(names and all(r.get("set") in names for r in rows)  # (a map that misses a row's set: folders)
               for names, rows in zip(sets, (a, b), strict=True))
    keys = body_keys(a, sets[0] if both else None), body_keys(b, sets[1] if both else None)
    for key_a, key_b, row_a, row_b in zip(*keys, a, b, strict=True):
        gait = (float(row_a["open_loop"]), float(row_b["open_loop"]))
        if key_a != key_b or not same_gait(*gait):
            raise ValueError(f"body {key_a} of {name_a} is not body {key_b} of {name_b} (its own gait "
                             f"{gait[0]:.6f} against {gait[1]:.6f}): the same bodies in the same order, evaluated "
                             "with the same --headings, --eval-episodes and seed")
    drifts = []
    for name in dict.fromkeys(key[0] for key in keys[0]):  # (set by set: a set under other settings moves whole)
        rows = [i for i, key in enumerate(keys[0]) if key[0] == name]
        drifts.append(check_drift([float(a[i]["open_loop"]) for i in rows], [float(b[i]["open_loop"]) for i in rows],
                                  f"{name_a} against {name_b}{f' (set {name})' if name else ''}"))
    return [d for d in drifts if d]


def compare(a: Path, b: Path) -> list[dict[str, object]]:
    """A − B per body for each of :data:`COLUMNS`: one row each (n, both means, the difference and its 99 % band,
    the fraction of bodies on which A moves further)."""
    made_by = "python -m lab.control --evaluate ... --bodies, or lab.heldout --pool"
    rows_a, rows_b = read_table(a, str(a), made_by), read_table(b, str(b), made_by)
    for rows, name in ((rows_a, a), (rows_b, b)):
        missing = [c for c in ("body", "open_loop", *COLUMNS.values()) if not rows or c not in rows[0]]
        if missing:
            raise ValueError(f"{name}: no {missing} column (a held-out bodies table of {made_by})")
    warn_hosts(same_bodies(rows_a, rows_b, str(a), str(b), (set_files(a), set_files(b))))
    out = []
    for what, column in COLUMNS.items():
        va, vb = (np.array([float(r[column]) for r in rows]) for rows in (rows_a, rows_b))
        mean, band = paired_band(va - vb)
        out.append({"what": what, "n": len(va), "a": round(float(va.mean()), 4), "b": round(float(vb.mean()), 4),
                    "a_minus_b": round(mean, 4), "band99": round(band, 4),
                    "a_further": round(float(np.mean(va > vb)), 4)})
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m lab.paired", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("a", type=Path, help="a held-out table (folder or bodies CSV)")
    p.add_argument("b", type=Path, help="the table it is compared with, same bodies")
    p.add_argument("--out", type=Path, default=None, help="also write the rows to this CSV")
    args = p.parse_args(argv)
    try:
        rows = compare(args.a, args.b)
    except ValueError as e:
        p.error(str(e))
    for r in rows:
        print(f"{r['what']}: {r['a']:.3f} against {r['b']:.3f}, A − B {r['a_minus_b']:+.3f} ± {r['band99']:.3f} "
              f"(99 %, {r['n']} bodies; A further on {100 * r['a_further']:.0f} %)")
    if args.out is not None:
        write_rows(args.out, rows)


if __name__ == "__main__":
    main()
