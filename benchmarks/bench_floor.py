"""The simulator's host floor: microseconds per simulated step when the physics costs nothing — one 2-voxel muscle
pair (or 128 of them), fixed dt — so what is left is the cost of issuing the work (Python, argument marshalling,
launches, thread-pool dispatch). On a GPU this floor, not the arithmetic, bounds a paper epoch (``docs/physics.md``,
"Host cost").

Rows, each the best of ``ROUNDS`` alternated runs of ``STEPS`` steps (kernels compiled beforehand): the ``flat``
schedule (the GPU's) with every launch from Python (``graph_launches=0``, as before compute graphs) and through a
compute graph of ``SimConfig.graph_launches`` launches, and the CPU's ``robots`` schedule; batch 1 and 128.

``python -m benchmarks floor``; ``FREEFORM_BENCH_ARCH=cuda`` on a GPU (the robots schedule is CPU-only),
``FREEFORM_BACKEND=quadrants`` for the other backend (it has no compute graphs: its graph row repeats the direct one).
"""

from __future__ import annotations

import os
import statistics
import time

import numpy as np

from freeform.sim import SimConfig, Simulator, runtime

STEPS = 400  # per timed run: 200 flat launches, a graph of 64 runs three times
ROUNDS = 7
BATCHES = (1, 128)


def muscle_pairs(batch: int) -> np.ndarray:
    """``batch`` bodies of two voxels, a muscle of each phase side by side: uint8 ``[batch, 2, 1, 1]``."""
    grids = np.zeros((batch, 2, 1, 1), np.uint8)
    grids[:, 0], grids[:, 1] = 2, 3
    return grids


def cases(arch: str) -> list[tuple[str, str, int]]:
    """(label, schedule, graph_launches) of every row on ``arch``."""
    graph = SimConfig().graph_launches
    rows = [("flat, launched from Python", "flat", 0), (f"flat, compute graph of {graph}", "flat", graph)]
    return rows + ([("robots (CPU)", "robots", 0)] if arch == "cpu" else [])


def main() -> None:
    arch = runtime.ensure(os.environ.get("FREEFORM_BENCH_ARCH", "auto"))
    engines = {}
    for label, schedule, launches in cases(arch):
        for batch in BATCHES:
            cfg = SimConfig(precision="f32", dt=1e-4, graph_launches=launches, burn_in=10.0, duration=10.0)
            sim = Simulator(cfg, arch=arch, schedule=schedule)
            engine = sim.engine(sim.layout(muscle_pairs(batch)))
            engine.advance(STEPS)  # compile (or load the cache) and build the graph outside the timings
            runtime.sync()
            engines[(label, batch)] = engine
    times: dict[tuple[str, int], list[float]] = {key: [] for key in engines}
    for r in range(ROUNDS):
        for key in (list(engines) if r % 2 == 0 else list(engines)[::-1]):  # alternate who runs first
            t0 = time.perf_counter()
            engines[key].advance(STEPS)
            runtime.sync()
            times[key].append((time.perf_counter() - t0) / STEPS * 1e6)
    print(f"{runtime.describe()} on {arch} ({runtime.num_threads()} threads); µs per simulated step, best | median of "
          f"{ROUNDS} alternated runs of {STEPS} steps; load average {os.getloadavg()[0]:.1f}")
    print(f"  {'':34s}" + "".join(f"{f'batch {b}':>20s}" for b in BATCHES))
    for label, _, _ in cases(arch):
        cells = "".join(f"{min(times[(label, b)]):10.1f} | {statistics.median(times[(label, b)]):6.1f}"
                        for b in BATCHES)
        print(f"  {label:34s}{cells}")


if __name__ == "__main__":
    main()
