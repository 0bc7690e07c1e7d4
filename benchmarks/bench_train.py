"""Training-application overhead: what logging, design records and checkpoints cost next to training itself.

Runs the CPU demo's configuration (``experiment=volume_cpu``) for a few epochs through ``freeform.train.train`` and
reports, per epoch, the seconds of PPO (rollout + update) and of the application's own work: cutting episodes,
writing the compressed design record, TensorBoard scalars (``perf/time_logging``) and the atomic checkpoint
(``perf/time_checkpoint``), and all of it together (an iteration's wall time minus PPO's). ``FREEFORM_BENCH_QUICK=1`` runs 3 epochs instead of 8.

The machine may be shared: timings only grow under contention, so the medians are pessimistic.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time

from freeform import train as train_mod
from freeform.config import compose


def main() -> None:
    epochs = 3 if os.environ.get("FREEFORM_BENCH_QUICK") else 8
    cfg = compose("experiment=volume_cpu", f"trainer.epochs={epochs}", "trainer.progress=false",
                  "trainer.print_every=0", "trainer.checkpoint_every=1")
    stamps: list[float] = []  # when each epoch's callbacks run: consecutive gaps = one whole loop iteration
    with tempfile.TemporaryDirectory() as run_dir:
        t0 = time.perf_counter()
        result = train_mod.train(cfg, run_dir, callbacks=[lambda ctx: stamps.append(time.perf_counter())])
        wall = time.perf_counter() - t0
    hist = result.history
    ppo = [h["perf/time_rollout"] + h["perf/time_update"] for h in hist]
    logging_ = [h["perf/time_logging"] for h in hist]
    ckpt = [h["perf/time_checkpoint"] for h in hist[1:]]  # each epoch reports the previous epoch's checkpoint
    # Everything in an iteration that is not PPO: episodes, record, scalars, flush, callbacks, checkpoint.
    app = [b - a - p for a, b, p in zip(stamps[:-1], stamps[1:], ppo[1:], strict=True)]
    med = {k: statistics.median(v) for k, v in (("ppo", ppo), ("log", logging_), ("ckpt", ckpt), ("app", app))}
    print(f"volume_cpu, {epochs} epochs, {cfg.env.num_envs} envs x T={cfg.env.steps}, rho={cfg.env.resolution}: "
          f"{wall:.1f} s wall (incl. start-up)")
    print(f"  PPO rollout + update              median {med['ppo'] * 1e3:8.1f} ms / epoch")
    for key, label in (("log", "episodes + record (time_logging)"), ("ckpt", "checkpoint (time_checkpoint)"),
                       ("app", "all of the app's work per epoch")):
        print(f"  {label:33s} median {med[key] * 1e3:8.1f} ms / epoch ({100 * med[key] / med['ppo']:.1f} % of PPO)")


if __name__ == "__main__":
    main()
