"""Open loop as a controller: the sine gait replayed through commands held for a control period converges to the
open-loop gait as the period shrinks (docs/control.md, "Equivalence").

Each robot's command for a period is the open-loop term sin(2π(t/T + φ)) held for the period (zero-order hold:
what a controller acting every ``period`` seconds can do), taken at the period's start or at its midpoint (the hold
a residual controller's base uses, ``ControlConfig.residual``: no half-period lag), then
``Engine.advance_time(period)``. After ``SECONDS`` the centre of mass's horizontal displacement is compared with the
open-loop engine's, robot by robot.

    python scripts/control_convergence.py            # 16 design bodies, f64, 1 s; ≈ 2 min on 2 cores

Run again by whoever changes the command path (``ControlEnv``'s commands, ``Engine.control_step``, the actuation's
hold or ramp): the convergence is what says a controller can play the open-loop gait at all.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SECONDS = 1.0
PERIODS = (0.05, 0.025, 0.0125, 0.00625, 0.003125, 0.0015625)


def main() -> None:
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies
    from freeform.sim import SimConfig, Simulator
    from freeform.sim.config import material_table
    from freeform.sim.state import MT

    grids = random_design_bodies(16, seed=1)
    cfg = SimConfig(precision="f64", burn_in=0.0, duration=SECONDS + 0.1)
    mt = material_table(cfg)

    def com_xy(engine, layout) -> np.ndarray:
        m = mt[MT.MASS][layout.material]
        p = engine.positions()
        r = layout.voxel_robot
        tot = np.bincount(r, weights=m)
        return np.stack([np.bincount(r, weights=m * p[:, k]) / tot for k in range(2)], 1)

    sim = Simulator(cfg, arch="cpu")
    layout = sim.layout(grids)
    start = com_xy(sim.engine(layout), layout)
    ref = sim.engine(layout)
    ref.advance_time(SECONDS)
    open_loop = np.linalg.norm(com_xy(ref, layout) - start, axis=1) / cfg.voxel_size
    phase = np.array([0.0] + [m.phase for m in cfg.materials])[layout.material]
    print(f"{layout.num_robots} design bodies, f64, {SECONDS} s; open-loop displacement {open_loop.mean():.3f} "
          f"voxels on average")
    print(f"{'period (s)':>11s} {'steps/period':>13s} {'hold at':>9s} {'mean |Δ| (voxels)':>18s} "
          f"{'mean |Δ| / open loop':>21s}")
    csim = Simulator(replace(cfg, actuation="command"), arch="cpu")
    for period in PERIODS:
        for at, offset in (("start", 0.0), ("midpoint", 0.5)):
            engine = csim.engine(csim.layout(grids))
            for k in range(round(SECONDS / period)):
                t = (k + offset) * period
                engine.set_commands(np.sin(2 * math.pi * (t / cfg.temp_period + phase)))
                engine.advance_time(period)
            moved = np.linalg.norm(com_xy(engine, layout) - start, axis=1) / cfg.voxel_size
            gap = np.abs(moved - open_loop)
            print(f"{period:11.5f} {period / float(np.median(ref.dt0)):13.0f} {at:>9s} {gap.mean():18.4f} "
                  f"{gap.mean() / open_loop.mean():21.1%}", flush=True)


if __name__ == "__main__":
    main()
