"""Where a block-schedule step's time goes on CUDA (issue 44 diagnostic): µs a step of 128 design bodies under
switches that each drop one part of the step (rl4design's ω² max, dynamic dt, the floor, B).

Run again on a GPU by whoever works on the block schedule (issue 59 reads its table: docs/physics.md):
``python scripts/probe_block_step.py`` from the repository root."""
import os
import sys

sys.path.insert(0, os.getcwd())
from benchmarks.bench_blocks import design_bodies, engine_for, us_per_step  # noqa: E402
from freeform.sim import SimConfig  # noqa: E402

grids = design_bodies(128)
paper = dict(precision="f32", semantics="rl4design", burn_in=100.0, duration=5.0)
cases = {
    "paper (rl4design, dynamic dt)": paper,
    "rl4design, fixed dt 1e-4": {**paper, "dt": 1e-4},
    "voxelyze, dynamic dt": {**paper, "semantics": "voxelyze"},
    "voxelyze, fixed dt, no floor, no gravity": {**paper, "semantics": "voxelyze", "dt": 1e-4, "floor": False, "gravity": 0.0},
}
for name, kw in cases.items():
    for b in ((None, 64) if name.startswith("paper") else (None,)):
        try:
            e = engine_for(grids, SimConfig(**kw), "cuda", "robots", b)
            print(f"{name:45s} B={e.block_dim:4d}: {us_per_step(e, 1024):6.2f} us a step", flush=True)
        except Exception as ex:
            print(name, "FAILED", type(ex).__name__, str(ex)[:200], flush=True)
