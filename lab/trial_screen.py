"""How well does a short trial predict the whole episode's? The zoo's candidates tried on a set of bodies, each
candidate's move kept after every decision, and what choosing by less would have given.

Two ways to spend fewer trial seconds than ``fit``'s (every candidate the whole episode):

* **short**: every candidate for ``d`` decisions, each body keeps the best by that move;
* **screen then finish**: every candidate for ``d`` decisions, each body's best ``k`` of them by that move played to
  the end, the best of those by the whole episode kept — ``C·d/D + k`` episodes' physics a body (k = 1: ``C·d/D``,
  the short trial alone) against ``C``
  (``D`` decisions an episode; the first ``d`` of the ``k`` replayed, which a simulator that could carry on a robot's
  episode would save).

Every figure is the chosen candidate's whole-episode move (the mean command, one episode, what ``fit`` reports),
as a fraction of the per-body reference (``lab.fractions``'s folders), beside ``fit``'s own choice:

    python -m lab.trial_screen lab/results/heldout_bodies/design_unseen.npy --out OUT \\
        --reference lab/results/reference/design_unseen32

Writes ``OUT/after.npy`` (``[D, C, M]``: each candidate's move after each decision), ``OUT/candidates.txt``,
``OUT/trials.csv`` (fit's trial columns: each candidate's whole-episode move, ``trial_<name>``, a row a body; what
``lab.fractions --table "NAME=OUT/trials.csv:trial_a|trial_b"`` chooses among) and ``OUT/screen.csv`` (one row a
rule: its episodes a body, its mean move, its fraction with a 99 % band, its paired difference to ``fit``'s choice).
``--also A B …`` plays more candidates in the same episode (their columns in ``after.npy`` and ``trials.csv``), left
out of the screen's rules.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from freeform.tables import paired_band, ratio_band, write_rows


def after_every_decision(grids: torch.Tensor, specs: tuple[str, ...], seed: int = 0) -> np.ndarray:
    """``[D, C, M]``: candidate c's move on body m after decision d, as ``fit``'s trials play them
    (``freeform.control.fit.trial_moves``)."""
    from freeform.control.fit import Candidates, trial_moves

    c = Candidates(specs, grids)
    if c.steering:
        raise ValueError("the screen is for walkers (headings any/fixed): a steering trial averages episodes")
    return trial_moves(c, grids, seed)


def screened(after: np.ndarray, d: int, k: int) -> np.ndarray:
    """Each body's chosen candidate ``[M]`` when every candidate plays ``d`` decisions and the best ``k`` by that
    move play the whole episode (k = 1: the short trial alone). A tie in the short move goes to the earlier
    candidate, as ``fit``'s; among the finished, a tie in the whole move to the better short mover."""
    short, whole = after[d - 1], after[-1]
    order = np.argsort(-short, axis=0, kind="stable")[:k]  # [k, M]: each body's best k by the short move
    best = np.take_along_axis(whole, order, 0).argmax(0)  # (among them, by the whole episode)
    return order[best, np.arange(after.shape[2])]


def rows_of(after: np.ndarray, reference: np.ndarray, rules: list[tuple[int, int]]) -> list[dict]:
    """One row a rule ``(d, k)``: episodes a body (physics, in whole episodes), the chosen moves' mean and fraction
    of ``reference`` ``[M]`` (99 % band, the delta method), and the paired difference to ``fit``'s choice."""
    steps, count, m = after.shape
    whole = after[-1]
    full = whole.max(0)
    rows = []
    for d, k in rules:
        moves = whole[screened(after, d, k), np.arange(m)]
        frac, band = ratio_band(moves, reference)
        diff, diff_band = paired_band(moves - full)
        physics = count * d / steps + (min(k, count) if k > 1 else 0)  # (k = 1: the short trial's pick is the figure)
        rows.append({"decisions": d, "finished": k, "episodes_a_body": round(physics, 3),
                     "mean_move": float(moves.mean()), "fraction": frac, "band": band,
                     "minus_full": diff, "minus_full_band": diff_band, "bodies_worse": int((moves < full - 1e-9).sum())})
    return rows


def main(argv: list[str] | None = None) -> None:
    from freeform import zoo
    from freeform.control.fit import candidate_name
    from lab.fractions import reference_moves

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bodies", type=Path)
    p.add_argument("--reference", type=Path, required=True,
                   help="lab.reference's folder for these bodies (A+B+…: a reference trained in parts)")
    p.add_argument("--candidates", nargs="+", default=list(zoo.TRIED))
    p.add_argument("--also", nargs="*", default=[], help="more candidates played, not screened")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.out.exists() and any(args.out.iterdir()):
        raise SystemExit(f"--out {args.out} holds files already: give a new folder (nothing is overwritten)")
    grids = torch.from_numpy(np.load(args.bodies)).to(torch.uint8)
    _, reference = reference_moves(args.reference)
    if len(reference) != len(grids):
        raise SystemExit(f"--reference {args.reference} holds {len(reference)} bodies, {args.bodies} {len(grids)}")
    t0 = time.perf_counter()
    played = after_every_decision(grids, (*args.candidates, *args.also), args.seed)
    seconds = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    np.save(args.out / "after.npy", played)
    names = [candidate_name(c) for c in (*args.candidates, *args.also)]
    (args.out / "candidates.txt").write_text("\n".join(names) + "\n")
    write_rows(args.out / "trials.csv", [{"body": m, **{f"trial_{n}": float(played[-1, k, m])
                                                        for k, n in enumerate(names)}} for m in range(len(grids))])
    after = played[:, : len(args.candidates)]
    steps = after.shape[0]
    rules = [(steps, 1)] + [(d, k) for d in range(1, steps) for k in (1, 2, 4, 8)]
    rows = rows_of(after, reference, rules)
    write_rows(args.out / "screen.csv", rows)
    print(f"trials of {len(names)} candidates on {len(grids)} bodies: {seconds / len(grids):.2f} s a body")
    for r in rows:
        print(f"d={r['decisions']} k={r['finished']}: {r['episodes_a_body']:6.2f} episodes a body, "
              f"{100 * r['fraction']:.1f} ± {100 * r['band']:.1f} %, against fit's {r['minus_full']:+.3f} ± "
              f"{r['minus_full_band']:.3f} a body ({r['bodies_worse']} worse)")


if __name__ == "__main__":
    main()
