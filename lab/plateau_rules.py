"""Where a plateau rule would stop a reference's run: ``trainer.plateau_window`` W and ``plateau_gain`` g read on the
evaluated curve (``trainer.plateau_on=eval_return``: one point every 10 epochs, the bodies' mean command), replayed
on ``lab.reference`` folders — on the measured curve (``curve.csv``: where the rule would have stopped it, and that
point's share of the folder's fitted plateau, ``asymptote.csv``) and on the fitted curve a − b·exp(−t/τ) itself,
continued past the run (what the rule costs and reaches on a curve of that τ without noise).

    python -m lab.plateau_rules lab/results/reference/steering_design_unseen32/part0_k4 \
        lab/results/reference/design_unseen32 --out lab/results/reference/plateau_rules.csv
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import replace
from pathlib import Path

import numpy as np

from freeform.config import TrainConfig
from freeform.run.trainer import flattened
from freeform.tables import write_rows

EVERY = 10
"""Epochs between two evaluated points (the steering teachers' ``agent.eval_every``; ``lab.reference``'s saves)."""


def first_stop(epochs: np.ndarray, curve: np.ndarray, window: int, gain: float) -> int | None:
    """The first of ``epochs`` after which the trainer's own rule (:func:`~freeform.run.trainer.flattened`, on the
    evaluated curve every :data:`EVERY` epochs) calls ``curve`` flat, or None."""
    base = TrainConfig()
    rule = replace(base, agent=replace(base.agent, eval_every=EVERY), trainer=replace(
        base.trainer, plateau_on="eval_return", plateau_window=window, plateau_gain=gain))
    points = [(int(e), float(v)) for e, v in zip(epochs, curve, strict=True) if e > 0 and e % EVERY == 0]
    return next((e for e, _ in points if flattened(rule, [], points, epoch=e)), None)


def rule_rows(folder: Path, windows: list[int], gains: list[float], until: int) -> list[dict]:
    """A row per rule for one ``lab.reference`` folder (module docstring)."""
    rows = list(csv.DictReader(open(folder / "curve.csv")))
    epochs = np.array([int(r["epoch"]) for r in rows])
    measured = np.array([float(r["mean_command"]) for r in rows])
    fit = next(csv.DictReader(open(folder / "asymptote.csv")))
    a, b, tau, t0 = (float(fit[k]) for k in ("asymptote", "b", "tau_epochs", "first_epoch"))
    t = np.arange(EVERY, until + 1, EVERY)
    fitted = a - b * np.exp(-(t - t0) / tau)
    at_measured = dict(zip(epochs.tolist(), measured, strict=True))
    at_fitted = dict(zip(t.tolist(), fitted, strict=True))
    out = []
    for window in windows:
        for gain in gains:
            seen, smooth = first_stop(epochs, measured, window, gain), first_stop(t, fitted, window, gain)
            out.append({"reference": str(folder), "tau_epochs": tau, "window": window, "gain": gain,
                        "stops_measured": seen if seen is not None else "",
                        "share_measured": float(at_measured[seen] / a) if seen else float("nan"),
                        "stops_fitted": smooth if smooth is not None else "",
                        "share_fitted": float(at_fitted[smooth] / a) if smooth else float("nan")})
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folders", type=Path, nargs="+", help="lab.reference folders (curve.csv, asymptote.csv)")
    p.add_argument("--windows", type=int, nargs="+", default=[20, 40, 80, 160])
    p.add_argument("--gains", type=float, nargs="+", default=[0.02, 0.01])
    p.add_argument("--until", type=int, default=3000, help="epochs the fitted curve is continued to")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if bad := [w for w in args.windows if w <= 0 or w % EVERY]:
        p.error(f"--windows {bad[0]}: a window of whole evaluations (a multiple of {EVERY} epochs)")
    if args.out.exists():
        p.error(f"--out {args.out} exists (nothing is overwritten)")
    rows = [r for folder in args.folders for r in rule_rows(folder, args.windows, args.gains, args.until)]
    write_rows(args.out, rows)
    for r in rows:
        print(f"{r['reference']}: W {r['window']} g {r['gain']:.0%}: measured {r['stops_measured'] or '-'} "
              f"({r['share_measured']:.0%}), fitted {r['stops_fitted'] or '-'} ({r['share_fitted']:.0%})")


if __name__ == "__main__":
    main()
