"""Which floating-point program ran the physics on this machine: a fingerprint of fixed simulations, to compare
across hosts (docs/physics-running.md, "Host independence").

    python scripts/physics_fingerprint.py OUT.npz                      # this host, this process's fast-math setting
    FREEFORM_FAST_MATH=0 python scripts/physics_fingerprint.py a.npz  # the strict path: the same bits on any x86-64
    qemu-x86_64 -cpu EPYC-Rome .venv/bin/python scripts/physics_fingerprint.py b.npz   # another CPU, emulated
    python scripts/physics_fingerprint.py --compare a.npz b.npz ...   # which cases differ, and by how much

Each case's final state is hashed (the bits) and saved. The cases: Voxelyze's 8³ settling cube (f64, the spec's
most rounding-sensitive reference: static friction locks in the transient's path), and 0.5 s of six actuated
design bodies on flat and rough ground, f32 and f64, on both schedules.

Run again by whoever touches a kernel, the engine or a compiler flag (before and after: the strict path must keep
the same bits), and on a new host or CPU to show host independence.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REC = 1.240490e-4  # VX recommendedTimeStep for ν = 0.35 (spec physics.md 15)


def simulate() -> dict[str, np.ndarray]:
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies
    from freeform.sim import SimConfig, Simulator, Terrain

    out: dict[str, np.ndarray] = {}
    sim = Simulator(SimConfig(precision="f64", temp_amplitude=0.0, dt=REC), arch="cpu")
    eng = sim.engine(sim.layout(np.full((1, 8, 8, 8), 1, dtype=np.uint8)))
    eng.advance(math.ceil(0.5 / REC))
    out["voxelyze_cube8_positions"] = eng.positions()
    bodies = random_design_bodies(6, seed=3).numpy()
    for ground, terrain in (("flat", Terrain()), ("rough", Terrain.rough(0.004, 0.05, seed=1))):
        for precision, schedule in (("f32", "robots"), ("f64", "robots"), ("f32", "flat"), ("f64", "flat")):
            cfg = SimConfig(precision=precision, burn_in=0.1, duration=0.4, terrain=terrain)
            r = Simulator(cfg, arch="cpu", schedule=schedule).simulate(bodies)
            for name in ("displacement", "com_end", "steps"):
                out[f"design_{ground}_{precision}_{schedule}_{name}"] = getattr(r, name).numpy()
    return out


def digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def compare(paths: list[Path]) -> None:
    runs = [np.load(p) for p in paths]
    ref = runs[0]
    for p, r in zip(paths, runs, strict=True):
        print(f"{p}: {r['host']} | {r['path']}")
    for key in sorted(k for k in ref.files if k not in ("host", "path")):
        row = []
        for r in runs[1:]:
            a, b = ref[key].astype(np.float64), r[key].astype(np.float64)
            row.append("same bits" if digest(ref[key]) == digest(r[key]) else
                       f"max |d| {np.abs(a - b).max():.2e} (rel {np.abs(a - b).max() / max(np.abs(a).max(), 1e-300):.1e})")
        print(f"  {key:44s} " + " | ".join(row))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, nargs="+", help="where to save this host's results (or, with --compare, "
                                                          "the saved results to compare, the first the reference)")
    parser.add_argument("--compare", action="store_true")
    args = parser.parse_args()
    if args.compare:
        compare(args.out)
        return
    from freeform.sim import runtime

    results = simulate()
    path = f"{runtime.describe()}, fast-math {'on' if runtime.fast_math() else 'off'}"
    host = f"CPU features: {runtime.cpu_features()}"
    print(f"{host} | {path}")
    for key, value in results.items():
        print(f"  {key:44s} {digest(value)}")
    np.savez(args.out[0], host=host, path=path, **results)


if __name__ == "__main__":
    main()
