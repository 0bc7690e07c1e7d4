"""Re-score a run's recorded designs under another protocol: is a reward what the task means, or the protocol's?

    python -m experiments.rescore runs/rl_vs_evolution/locomotion/* --set sim.burn_in=2.0 --out figures/rescore

For each run, the final grids of its first and last recorded epochs (``--epochs``; at most ``--designs`` of each)
are scored twice by the run's own task: with the run's config as it trained (this reproduces the recorded
rewards) and with the ``--set`` overrides (dotted keys of the run's config). The mean of each, with its 99 % band,
per run and epoch. The question it answers for the CPU demos: a burn-in of 0.25 s ends before a tall body has
finished falling over, so a design that topples in the evaluation window scores its fall as locomotion;
``--set sim.burn_in=2.0`` starts the evaluation after nearly every body has landed (1 s is not enough for the
tallest: docs/tasks.md, "Falling is not walking"). Writes ``rescore.csv``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from experiments import common


def pick_epochs(epochs: Sequence[int], spec: str) -> list[int]:
    """Recorded epochs named by ``spec``: comma-separated ``first``, ``last`` or epoch numbers."""
    out = []
    for token in (t.strip() for t in spec.split(",") if t.strip()):
        if token in ("first", "last"):
            out.append(epochs[0] if token == "first" else epochs[-1])
        elif token.isdigit() and int(token) in epochs:
            out.append(int(token))
        else:
            raise ValueError(f"--epochs entries must be 'first', 'last' or a recorded epoch, got {token!r}; this "
                             f"run recorded epochs {epochs[0]}..{epochs[-1]} ({len(epochs)} records)")
    return list(dict.fromkeys(out))


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    common.add_overrides(p, "for the second scoring")
    p.add_argument("--epochs", default="first,last", help="recorded epochs: first, last or numbers (default both)")
    p.add_argument("--designs", type=int, default=64, help="at most this many designs of each epoch (default 64)")
    p.add_argument("--device", default="cpu", help="torch device of the task (cpu | cuda[:i])")
    args = p.parse_args(argv)
    if not args.overrides:
        raise ValueError("--set: give at least one KEY=VALUE override to score the designs under")
    if args.designs < 2:
        raise ValueError(f"--designs must be >= 2 (a band needs two), got {args.designs}")
    from experiments.robustness import run_train_config
    from freeform.records import list_records, read_record, record_epoch, record_path
    from freeform.train import build_task

    device = torch.device(args.device)
    runs = common.find_runs(args.paths)
    rows: dict[str, list] = {k: [] for k in ("run", "epoch", "n", "recorded", "as_trained", "as_trained_band",
                                             "rescored", "rescored_band")}
    for run in runs:
        epochs = [record_epoch(path) for path in list_records(run)]
        if not epochs:
            raise ValueError(f"paths: run {run} has no design records (records/epoch_*.npz)")
        tasks = [build_task(run_train_config(run, o), device) for o in ((), args.overrides)]
        for epoch in pick_epochs(epochs, args.epochs):
            record = read_record(record_path(run, epoch))
            grids = torch.from_numpy(np.ascontiguousarray(record.final_grids[: args.designs])).to(device)
            scores = [task.reward(grids).double().cpu().numpy() for task in tasks]
            (trained, trained_half), (rescored, rescored_half) = (common.mean_band(s) for s in scores)
            recorded = float(np.mean(record.rewards[: args.designs]))
            for key, value in zip(rows, (str(run), epoch, len(grids), recorded, float(trained), float(trained_half),
                                         float(rescored), float(rescored_half)), strict=True):
                rows[key].append(value)
            print(f"{run.name} epoch {epoch:4d} (n = {len(grids)}): recorded {recorded:.3f}, as trained "
                  f"{trained:.3f} ± {trained_half:.3f}, with {' '.join(args.overrides)} {rescored:.3f} ± "
                  f"{rescored_half:.3f}")
    prov = common.provenance(runs)
    prov["overrides"] = " ".join(args.overrides)
    out = {"csv": common.write_csv(args.out / "rescore.csv", rows, prov)}
    print("wrote " + str(out["csv"]))
    return out


if __name__ == "__main__":
    common.run_cli(main)
