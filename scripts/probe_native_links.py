"""What the CPU simulator's link phase costs compiled outside Taichi (issue 43, docs/physics.md "The link phase in
C++, probed"): ``scripts/native_links.cpp`` — the same link update as ``freeform/sim/links.py`` on the f32 path, on
the engine's own packed buffers — built with g++ for this host and run two ways: one link at a time with
Voxelyze's branches, and 16 links per instruction along the common path (a small-angle link whose end rotation
takes atan's series; the lanes off it through the branching update). Each is checked against Taichi's link phase on
the same state and timed beside it, one thread.

    python scripts/probe_native_links.py              # ~30 s: 128 design bodies, f32, 300 warm steps, 200 timed

The workload is ``scripts/profile_sim.py``'s (``benchmarks.bench_sim.random_design_bodies``, seed 0, the paper's
fixed dt): after ``--warm`` steps of the production kernel the state is saved, and each contender runs ``--steps``
link phases of every robot from it (the voxels stand still: profile_sim's ``links`` segment). Agreement: one link
phase from the saved state by each against Taichi's — every link's end loads, pose, rotation vectors, strain and
flags — as the largest difference per column relative to that column's largest magnitude (fast-math on both
sides: contractions differ, so the bits do not; the damping loads scale a difference of successive poses, which
magnifies rounding).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import argparse
import ctypes
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOURCE = Path(__file__).with_name("native_links.cpp")
# -ffast-math as the simulator's production path; -mtune=native lets g++ use the host's gather instructions
FLAGS = ["-O3", "-march=native", "-mtune=native", "-ffast-math", "-shared", "-fPIC", "-std=c++17"]
CONTENDERS = {"C++, one link": "link_steps_scalar", "C++, 16 links": "link_steps_vector"}


def layout_header() -> str:
    """``layout.h``: every column index and width of ``freeform/sim/state.py``'s tables, the header's offsets, the
    flags and the model's thresholds, as the C++ reads them (one source of the layout: state.py)."""
    from freeform.sim import links, quat
    from freeform.sim.state import DIVERGED, GP, HDR, LI, LR, LT, MT, RI, RT, SMALL, VALID, VI, VR

    lines = ["#pragma once"]
    for prefix, table in (("VR", VR), ("VI", VI), ("LR", LR), ("LI", LI), ("RT", RT), ("RI", RI), ("MT", MT),
                          ("LT", LT), ("GP", GP), ("HDR", HDR)):
        lines.append(f"constexpr int {prefix}_W = {table.width};")
        lines += [f"constexpr int {prefix}_{col} = {getattr(table, col)};" for col in table.columns]
    lines += [f"constexpr int FLAG_SMALL = {SMALL}, FLAG_VALID = {VALID}, STATUS_DIVERGED = {DIVERGED};",
              f"constexpr float SA_BEND = {links.SA_BOND_BEND_RAD}f, SA_EXT = {links.SA_BOND_EXT_PERC}f, "
              f"HYST = {links.HYSTERESIS_FACTOR}f;",
              f"constexpr float ATAN_SERIES_X2 = {quat.ATAN_SERIES_X2}f, POSX_SMALL = {quat.POSX_SMALL}f;",
              f"constexpr double POSX_PI_EPS = {quat.POSX_PI_EPS};"]
    return "\n".join(lines) + "\n"


def build(tmp: Path) -> dict:
    """``native_links.cpp`` compiled (g++, this host's instruction set): {contender: its ctypes function}."""
    (tmp / "layout.h").write_text(layout_header())
    lib = tmp / "native_links.so"
    subprocess.run(["g++", *FLAGS, f"-I{tmp}", "-o", str(lib), str(SOURCE)], check=True)
    so = ctypes.CDLL(str(lib))
    out = {}
    for name, symbol in CONTENDERS.items():
        fn = getattr(so, symbol)
        fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
        fn.restype = ctypes.c_long
        out[name] = fn
    return out


def compared(native: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict[str, float]:
    """Per LR column group (and the flags): max |native − truth| / max |truth| over every link."""
    from freeform.sim.state import HDR, LI, LR

    h = truth["ints"]
    links = h[HDR.N_LINKS]
    rows = {}
    for name, (buf, at, width) in {"lr": ("reals", h[HDR.LR_AT], LR.width), "li": ("ints", h[HDR.LI_AT], LI.width)}.items():
        rows[name] = tuple(b[buf][at: at + links * width].reshape(links, width) for b in (native, truth))
    out = {}
    for col in ("FN", "FP", "MN", "MP", "P2", "A1", "A2", "STRAIN"):
        a, b = (x[:, LR.span(col)].astype(np.float64) for x in rows["lr"])
        out[col] = float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
    a, b = (x[:, LI.FLAGS] for x in rows["li"])
    out["flags differ"] = float((a != b).sum())
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

    cfg = SimConfig(precision="f32", dt=DT, burn_in=0.0, duration=1e9)
    eng = Simulator(cfg, arch="cpu", schedule="robots").engine(
        Simulator(cfg, arch="cpu").layout(random_design_bodies(args.bodies, seed=0)))
    if eng.order != "aos" or cfg.semantics != "voxelyze":
        raise SystemExit("the C++ link update reads the robots schedule's aos buffers under Voxelyze semantics")
    taichi_links = phase_kernels("f32", eng.switches)[0]
    buffers = tuple(eng._buffers[name] for name in BUFFERS)
    eng.advance(args.warm)
    saved = eng.snapshot()
    start = {name: saved["buffers"][name].copy() for name in BUFFERS}
    taichi_links(*buffers, 1)
    runtime.sync()
    truth = {name: runtime.to_numpy(eng._buffers[name]).copy() for name in BUFFERS}

    with tempfile.TemporaryDirectory() as tmp:
        libs = build(Path(tmp))
        contenders = {"Taichi": None, **libs}
        print(f"{args.bodies} design bodies: {eng.layout.num_voxels} voxels, {eng.layout.num_links} links; f32, fast-math "
              f"{'on' if runtime.fast_math() else 'off'}; {runtime.describe()}; CPU {runtime.cpu_features()}")
        for name, fn in libs.items():
            state = {k: v.copy() for k, v in start.items()}
            slow = fn(*(state[k].ctypes.data for k in BUFFERS), 1)
            worst = compared(state, truth)
            print(f"  {name:14s} against Taichi, one link phase ({slow} of {eng.layout.num_links} links by the "
                  "branching update): " +
                  ", ".join(f"{k} {v:.1e}" if k != "flags differ" else f"{k} {int(v)}" for k, v in worst.items()))
        times = {}
        for _ in range(args.repeat):  # (alternated, best of each)
            for name, fn in contenders.items():
                if fn is None:
                    eng.restore(saved)
                    runtime.sync()
                    c0 = time.process_time()
                    taichi_links(*buffers, args.steps)
                    runtime.sync()
                else:
                    state = {k: v.copy() for k, v in start.items()}
                    c0 = time.process_time()
                    fn(*(state[k].ctypes.data for k in BUFFERS), args.steps)
                times[name] = min(times.get(name, float("inf")), time.process_time() - c0)
        link_steps = eng.layout.num_links * args.steps
        for name, t in times.items():
            print(f"  {name:14s} {1e9 * t / link_steps:7.1f} ns per link-step ({times['Taichi'] / t:4.2f}x Taichi), "
                  f"one thread, best of {args.repeat}")


if __name__ == "__main__":
    main()
