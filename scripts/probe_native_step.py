"""What the CPU simulator's step costs compiled outside Taichi (issue 43, docs/physics.md "The step in C++,
probed"): ``freeform/sim/native_step.cpp`` (the native schedule's step) — the same link and voxel updates as ``freeform/sim/links.py`` and
``voxels.py`` on the f32 path (Voxelyze semantics, fixed dt, the flat floor, the sine's actuation), on the engine's
own packed buffers — built with g++ for this host and run two ways: one item at a time with Voxelyze's branches,
and 16 items per AVX-512 instruction along the common path (the lanes off it through the branching updates). Each
is checked against Taichi's kernels on the same state and timed beside them, one thread.

    python scripts/probe_native_step.py              # ~1 min: 128 design bodies, f32, 300 warm steps, 200 timed

The workload and the segments are ``scripts/profile_sim.py``'s (``benchmarks.bench_sim.random_design_bodies``,
seed 0, the paper's fixed dt): after ``--warm`` steps of the production kernel the state is saved, and each
contender runs ``--steps`` steps of every robot from it, its link phase only (``links``: the voxels stand still)
and its link and voxel phases (``links+voxels``; no robot phase: the clock stands still). Agreement: one step from
the saved state by each against Taichi's — every link's end loads, pose, rotation vectors, strain and flags, every
voxel's pose, momenta, Poisson terms, rest size and flags — as the largest difference per column relative to that
column's largest magnitude (fast-math on both sides: contractions differ, so the bits do not; the damping loads
scale a difference of successive poses, which magnifies rounding).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# per segment (profile_sim's), the C++ entry points (freeform/sim/native_step.cpp): one item at a time, 16 at once
SEGMENTS = {"links": ("links_scalar", "links_vector"), "links+voxels": ("links_voxels_scalar", "links_voxels_vector")}


def build() -> dict:
    """The native schedule's library (``freeform.sim.native.library``: compiled for this host on first use):
    {segment: (one at a time, 16 at once) ctypes functions}."""
    from freeform.sim import native

    lib = native.library()
    return {segment: tuple(getattr(lib, symbol) for symbol in symbols) for segment, symbols in SEGMENTS.items()}


def compared(native: dict[str, np.ndarray], truth: dict[str, np.ndarray], voxels: bool) -> dict[str, float]:
    """Per column (the links', and with ``voxels`` the voxels' state): max |native − truth| / max |truth| over
    every item; the flags: how many items differ."""
    from freeform.sim.state import HDR, LI, LR, VI, VR

    h = truth["ints"]
    tables = {"lr": ("reals", h[HDR.LR_AT], LR, h[HDR.N_LINKS]), "li": ("ints", h[HDR.LI_AT], LI, h[HDR.N_LINKS]),
              "vr": ("reals", h[HDR.VR_AT], VR, h[HDR.N_VOXELS]), "vi": ("ints", h[HDR.VI_AT], VI, h[HDR.N_VOXELS])}
    rows = {name: tuple(b[buf][at: at + n * t.width].reshape(n, t.width) for b in (native, truth))
            for name, (buf, at, t, n) in tables.items()}
    columns = [("lr", c) for c in ("FN", "FP", "MN", "MP", "P2", "A1", "A2", "STRAIN")]
    if voxels:
        columns += [("vr", c) for c in ("POS", "MOM", "ORI", "AMOM", "TAREA", "TSUM", "SIZE")]
    out = {}
    for table, col in columns:
        a, b = (x[:, tables[table][2].span(col)].astype(np.float64) for x in rows[table])
        out[col] = float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
    out["link flags differ"] = float((rows["li"][0][:, LI.FLAGS] != rows["li"][1][:, LI.FLAGS]).sum())
    if voxels:
        out["voxel flags differ"] = float((rows["vi"][0][:, VI.FLAGS] != rows["vi"][1][:, VI.FLAGS]).sum())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bodies", type=int, default=128)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--warm", type=int, default=300)
    parser.add_argument("--repeat", type=int, default=3, help="best of this many")
    args = parser.parse_args()
    os.environ.setdefault("TI_CPU_MAX_NUM_THREADS", "1")
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "scripts"))
    from profile_sim import DT, phase_kernels

    from benchmarks.bench_sim import random_design_bodies
    from freeform.sim import SimConfig, Simulator, runtime
    from freeform.sim.state import BUFFERS
    from freeform.sim.terrain import FLAT

    cfg = SimConfig(precision="f32", dt=DT, burn_in=0.0, duration=1e9)
    eng = Simulator(cfg, arch="cpu", schedule="robots").engine(
        Simulator(cfg, arch="cpu").layout(random_design_bodies(args.bodies, seed=0)))
    sw = eng.switches
    if eng.order != "aos" or (sw.floor, sw.terrain, sw.rl4design, sw.dynamic_dt, sw.command) != (1, FLAT, 0, 0, 0):
        raise SystemExit("the C++ step covers the robots schedule's aos buffers, Voxelyze semantics, a fixed dt, the "
                         f"flat floor and the sine's actuation; this engine: {sw}")
    taichi = dict(zip(SEGMENTS, phase_kernels("f32", sw), strict=True))
    buffers = tuple(eng._buffers[name] for name in BUFFERS)
    eng.advance(args.warm)
    saved = eng.snapshot()
    start = {name: saved["buffers"][name].copy() for name in BUFFERS}

    def run_taichi(segment: str, n: int) -> None:
        eng.restore(saved)
        runtime.sync()
        taichi[segment](*buffers, n)
        runtime.sync()

    def run_native(fn, n: int) -> tuple[dict, int]:
        state = {k: v.copy() for k, v in start.items()}
        return state, fn(*(state[k].ctypes.data for k in BUFFERS), n, 1)

    print(f"{args.bodies} design bodies: {eng.layout.num_voxels} voxels, {eng.layout.num_links} links; f32, fast-math "
          f"{'on' if runtime.fast_math() else 'off'}; {runtime.describe()}; CPU {runtime.cpu_features()}")
    native = build()
    for segment, fns in native.items():
        run_taichi(segment, 1)
        truth = {name: runtime.to_numpy(eng._buffers[name]).copy() for name in BUFFERS}
        items = eng.layout.num_links + (eng.layout.num_voxels if segment != "links" else 0)
        for how, fn in zip(("one at a time", "16 at once"), fns, strict=True):
            state, slow = run_native(fn, 1)
            worst = compared(state, truth, voxels=segment != "links")
            print(f"  {segment}, C++ {how}, against Taichi after one step ({slow} of {items} items by the branching "
                  "updates): " + ", ".join(f"{k} {v:.1e}" if "differ" not in k else f"{k} {int(v)}"
                                           for k, v in worst.items()))
    times: dict[tuple[str, str], float] = {}
    for _ in range(args.repeat):  # (alternated, best of each)
        for segment, fns in native.items():
            for how, fn in (("Taichi", None), ("C++ one at a time", fns[0]), ("C++ 16 at once", fns[1])):
                if fn is None:
                    eng.restore(saved)
                    runtime.sync()
                c0 = time.process_time()
                if fn is None:
                    taichi[segment](*buffers, args.steps)
                    runtime.sync()
                else:
                    state = {k: v.copy() for k, v in start.items()}
                    c0 = time.process_time()
                    fn(*(state[k].ctypes.data for k in BUFFERS), args.steps, 1)
                times[segment, how] = min(times.get((segment, how), float("inf")), time.process_time() - c0)
    voxel_steps, link_steps = eng.layout.num_voxels * args.steps, eng.layout.num_links * args.steps
    print(f"  ns per voxel-step (link phase also per link-step), one thread, best of {args.repeat}:")
    for how in ("Taichi", "C++ one at a time", "C++ 16 at once"):
        lk, both = times["links", how], times["links+voxels", how]
        speed = {k: times[k, "Taichi"] / times[k, how] for k in SEGMENTS}
        print(f"    {how:18s} link phase {1e9 * lk / voxel_steps:6.1f} ({1e9 * lk / link_steps:5.1f} per link, "
              f"x{speed['links']:.2f})  voxel phase {1e9 * (both - lk) / voxel_steps:6.1f}  both "
              f"{1e9 * both / voxel_steps:6.1f} (x{speed['links+voxels']:.2f})")
    # the whole batch on every core: wall-clock M voxel-steps/s of the 16-lane step by 1 and 2 workers (OpenMP over
    # robots), against what one of Taichi's threads does (x the cores: its robots schedule scales so, docs/physics.md)
    wall = {}
    for _ in range(args.repeat):
        for threads in (1, 2):
            state = {k: v.copy() for k, v in start.items()}
            w0 = time.perf_counter()
            native["links+voxels"][1](*(state[k].ctypes.data for k in BUFFERS), args.steps, threads)
            wall[threads] = min(wall.get(threads, float("inf")), time.perf_counter() - w0)
    print("  C++ 16 at once, whole batch, wall clock: " + ", ".join(
        f"{threads} thread{'s' if threads > 1 else ''} {voxel_steps / t / 1e6:.1f} M voxel-steps/s"
        for threads, t in wall.items()) + f"; Taichi one thread {voxel_steps / times['links+voxels', 'Taichi'] / 1e6:.1f}")


if __name__ == "__main__":
    main()
