"""Whether a design or co-design run's designs collapse as it trains: the designs of its first and its last K epochs
(``records/epoch_*.npz``), each window's pooled, their spread (``freeform.body.diversity``: ``distance``, the mean
pairwise fraction of cells whose material differs, bodies moved to their grid's corner; ``distinct``, how many
different bodies) beside the window's mean return and body volume::

    freeform-train experiment=codesign_student_steering_cpu hydra.run.dir=runs/codesign_student_steering
    python -m experiments.design_diversity runs/codesign_student_steering runs/<another run> --epochs 4 \\
        --out runs/diversity.csv

A co-design preset's epoch designs 64 bodies, so 4 epochs pool 256. A collapse onto one design shows as
``distinct`` falling towards 1 and ``distance`` towards 0 from the first window to the last (ECo-MoE's warning for a
universal controller co-optimised with its designs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments.common import run_cli, write_rows


def windows(run: Path, epochs: int) -> list[dict[str, Any]]:
    """The rows of ``run``: its first and its last ``epochs`` epochs of design records, each window's designs pooled
    (``ValueError`` naming the run if it has fewer than ``2 * epochs`` records: the windows must not overlap)."""
    from freeform.body import diversity
    from freeform.records import list_records, read_record

    if not Path(run).is_dir():
        raise ValueError(f"{run}: no such run directory")
    paths = list_records(run)
    if len(paths) < 2 * epochs:
        raise ValueError(f"{run}: {len(paths)} epochs of design records (records/epoch_*.npz), but --epochs {epochs} "
                         f"needs at least {2 * epochs} (a first and a last window apart)")
    rows = []
    for name, chosen in (("first", paths[:epochs]), ("last", paths[-epochs:])):
        records = [read_record(p) for p in chosen]
        grids = np.concatenate([r.final_grids for r in records])
        if len(grids) < 2:
            raise ValueError(f"{run}: its {name} {epochs} epochs hold {len(grids)} design; a spread needs at least 2 "
                             "(a larger --epochs)")
        volume = np.concatenate([r.metrics.get("volume", np.full(r.num_episodes, np.nan)) for r in records])
        rows.append({"run": str(run), "window": f"{name} {epochs} epochs",
                     "epochs": f"{records[0].epoch}-{records[-1].epoch}", "designs": len(grids),
                     **diversity(torch.from_numpy(np.ascontiguousarray(grids))),
                     "return": float(np.mean(np.concatenate([r.rewards for r in records]))),
                     "volume": float(np.mean(volume))})
    return rows


def main(argv: list[str] | None = None) -> Path:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="design or co-design run directories")
    p.add_argument("--epochs", type=int, default=4, help="epochs in each window (default 4)")
    p.add_argument("--out", type=Path, required=True, help="the CSV to write (refused if it exists)")
    args = p.parse_args(argv)
    if args.epochs < 1:
        raise ValueError(f"--epochs must be at least 1, got {args.epochs}")
    if args.out.exists():
        raise ValueError(f"--out {args.out} exists; give a new path (nothing is overwritten)")
    rows = [row for run in args.runs for row in windows(run, args.epochs)]
    for row in rows:
        print(f"{row['run']} {row['window']}: distance {row['distance']:.3f}, {row['distinct']} distinct of "
              f"{row['designs']}, return {row['return']:.3f}, volume {row['volume']:.1f}")
    return write_rows(args.out, rows)


if __name__ == "__main__":
    run_cli(main)
