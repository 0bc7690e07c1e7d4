"""Where the CPU simulator's instructions go: instructions per voxel-step of the robots schedule, split by phase
(docs/physics.md, "Where the instructions go (CPU)").

    python scripts/profile_sim.py                  # re-runs itself under valgrind's callgrind, one thread
    python scripts/profile_sim.py --native         # the same segments timed natively (ns per voxel-step)
    FREEFORM_FAST_MATH=0 python scripts/profile_sim.py   # the strict path
    python scripts/profile_sim.py --schedule native       # the native step (native.py), built for x86-64-v3

The workload: ``--bodies`` untrained design bodies (``benchmarks.bench_sim.random_design_bodies``, seed 0: the
sim benchmark's bodies), f32 unless ``--precision f64``, the paper's fixed dt, ``--warm`` steps first (natively
uninstrumented under valgrind), then three segments of ``--steps`` steps from the same saved state:

* ``step``: the production kernel (``run_robots``, one worker): what ``Engine.advance`` runs;
* ``links``: the same robots and steps, every link's ``link_update`` only (the voxels stand still);
* ``links+voxels``: each step every link's ``link_update`` then every voxel's ``voxel_update``, no robot phase.

With ``--schedule native`` the segments are the native step's entry points (``advance``, ``links_vector``,
``links_voxels_vector``: a group of lanes at once, one thread), on the fast-math path; valgrind presents AVX2 and no
AVX-512, so the library is built for x86-64-v3 (8 lanes; ``$FREEFORM_NATIVE_ARCH``, also for ``--native`` timings,
so that both measure one program: ``FREEFORM_NATIVE_ARCH=native --native`` times the host's own build).

voxel phase = ``links+voxels`` − ``links``; bookkeeping (robot phase: clock, status, actuation phase, events, the
queue and the per-step checks) = ``step`` − ``links+voxels``. Callgrind counts instructions exactly, whatever the
machine's load; the counts are the JIT code's (the segments are cut with callgrind's client requests around each
kernel call, so Python and compilation are outside them; one launch's host cost, ~1e5 instructions, is inside).

Run again by whoever changes the CPU step (a kernel, the access layer, the native step, the Taichi or quadrants
version): the instructions per voxel-step are the CPU's figure of merit, exact whatever the machine's load.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import argparse
import ctypes
import glob
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DT = 1.1785e-4
SHIM = r"""
#include <valgrind/callgrind.h>
void cg_start(void) { CALLGRIND_START_INSTRUMENTATION; }
void cg_stop(void) { CALLGRIND_STOP_INSTRUMENTATION; }
void cg_zero(void) { CALLGRIND_ZERO_STATS; }
void cg_dump(const char *s) { CALLGRIND_DUMP_STATS_AT(s); }
int cg_running(void) { return RUNNING_ON_VALGRIND; }
"""


def callgrind_shim(tmp: Path):
    """ctypes handle of a tiny library of callgrind's client requests (compiled here: they are macros)."""
    src, lib = tmp / "cg.c", tmp / "cg.so"
    src.write_text(SHIM)
    subprocess.run(["cc", "-O1", "-shared", "-fPIC", "-o", str(lib), str(src)], check=True)
    return ctypes.CDLL(str(lib))


def phase_kernels(precision: str, switches):
    """``links(reals, ints, f64s, n)`` and ``links_voxels(...)``: each robot in turn, ``n`` steps of its link
    phase (and voxel phase), by the same ``ti.func``s as ``run_robots``, on one thread."""
    from freeform.sim.access import make_access
    from freeform.sim.links import make_links
    from freeform.sim.runtime import ti
    from freeform.sim.state import HDR, RI
    from freeform.sim.voxels import make_voxels

    acc = make_access(precision, "aos")
    ld, header, bind = acc.ld, acc.header, acc.bind
    Reals, Ints, F64s = acc.Buffer["reals"], acc.Buffer["ints"], acc.Buffer["f64s"]
    link_update = make_links(precision, "aos").link_update
    voxel_update = make_voxels(precision, "aos").voxel_update

    def build(with_voxels: bool):
        @ti.func
        def robot_steps(r, s: ti.template(), n_steps):
            for _ in range(n_steps):
                for lk in range(ld(s.ri, RI.LSTART, r), ld(s.ri, RI.LEND, r)):
                    link_update(lk, r, s)
                if ti.static(with_voxels):
                    for v in range(ld(s.ri, RI.VSTART, r), ld(s.ri, RI.VEND, r)):
                        voxel_update(v, s)

        @ti.kernel
        def run(reals: Reals, ints: Ints, f64s: F64s, n_steps: ti.i32):
            ti.loop_config(serialize=True)
            for r in range(ints[HDR.N_ROBOTS]):
                h = header(ints)
                robot_steps(r, bind(reals, ints, f64s, h, switches), n_steps)
        return run

    return build(False), build(True)


def measure(args, cg) -> dict[str, float]:
    """{segment: instructions (callgrind) or seconds of CPU time (native, best of ``--repeat``)}."""
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies
    from freeform.sim import SimConfig, Simulator, runtime
    from freeform.sim.state import BUFFERS

    bodies = random_design_bodies(args.bodies, seed=0)
    cfg = SimConfig(precision=args.precision, dt=DT, burn_in=0.0, duration=1e9)
    eng = Simulator(cfg, arch="cpu", schedule=args.schedule).engine(Simulator(cfg, arch="cpu").layout(bodies))
    buffers = tuple(eng._buffers[name] for name in BUFFERS)
    if args.schedule == "native":
        from freeform.sim import native

        lib, at = native.library(), tuple(b.ctypes.data for b in buffers)
        floor, command = int(eng.switches.floor), int(eng.switches.command)
        segments = {"step": lambda n: lib.advance(*at, n, 1, floor, command),
                    "links": lambda n: lib.links_vector(*at, n, 1),
                    "links+voxels": lambda n: lib.links_voxels_vector(*at, n, 1)}
    else:
        links, links_voxels = phase_kernels(args.precision, eng.switches)
        segments = {"step": lambda n: eng.kernels.run_robots(*buffers, n, 1),
                    "links": lambda n: links(*buffers, n),
                    "links+voxels": lambda n: links_voxels(*buffers, n)}
    eng.advance(args.warm)
    saved = eng.snapshot()
    for run in segments.values():  # compile outside the counts
        run(1)
        eng.restore(saved)
    runtime.sync()
    out = {}
    for name, run in segments.items():
        best = float("inf")
        for _ in range(1 if cg else args.repeat):
            eng.restore(saved)
            runtime.sync()
            if cg:
                cg.cg_start()
                cg.cg_dump(b"start")  # (a dump resets the counts; callgrind's ZERO_STATS miscounts here)
            c0 = time.process_time()
            run(args.steps)
            runtime.sync()
            best = min(best, time.process_time() - c0)
            if cg:
                cg.cg_dump(name.encode())
                cg.cg_stop()
                best = dumped_instructions(name)
        out[name] = best
    out["voxel_steps"] = eng.layout.num_voxels * args.steps
    out["link_steps"] = eng.layout.num_links * args.steps
    return out


def dumped_instructions(name: str) -> float:
    """The instruction count of callgrind's dump of segment ``name`` (the dump file is removed)."""
    for f in glob.glob(f"{os.environ['PROFILE_SIM_OUT']}/cg.out*"):
        text = Path(f).read_text(errors="replace")
        if f"\ndesc: Trigger: Client Request: {name}\n" in text:
            if os.environ.get("PROFILE_SIM_ANNOTATE") and name == "step":  # the top functions (libm's by name)
                print(subprocess.run(["callgrind_annotate", "--inclusive=no", f], capture_output=True,
                                     text=True).stdout[:3000])
            for g in glob.glob(f"{os.environ['PROFILE_SIM_OUT']}/cg.out*"):
                os.remove(g)
            return float(next(line.split()[1] for line in text.splitlines() if line.startswith("summary:")))
    raise SystemExit(f"no callgrind dump for {name}")


def report(values: dict[str, float], unit: str, scale: float, args) -> None:
    vs, ls = values["voxel_steps"], values["link_steps"]
    step, lk, lv = values["step"], values["links"], values["links+voxels"]
    parts = {"link phase": lk, "voxel phase": lv - lk, "bookkeeping (robot phase)": step - lv}
    from freeform.sim import native, runtime

    target = f"native step built for {native.built_for()}" if args.schedule == "native" else "robots"
    print(f"{target}: {args.bodies} design bodies, {args.precision}, {args.steps} steps after {args.warm}: "
          f"{vs / args.steps:.0f} voxels, {ls / vs:.2f} links per voxel; {runtime.describe()}, fast-math "
          f"{'on' if runtime.fast_math() else 'off'}, CPU {runtime.cpu_features()}")
    print(f"  {'whole step':28s} {step * scale / vs:9.1f} {unit} per voxel-step")
    for name, v in parts.items():
        extra = f"  ({v * scale / ls:.1f} per link-step)" if name == "link phase" else ""
        print(f"  {name:28s} {v * scale / vs:9.1f} {unit} per voxel-step  {100 * v / step:5.1f} %{extra}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bodies", type=int, default=128)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--warm", type=int, default=300, help="steps run before the segments (uncounted)")
    parser.add_argument("--precision", default="f32", choices=("f32", "f64"))
    parser.add_argument("--schedule", default="robots", choices=("robots", "native"),
                        help="the robots schedule's Taichi kernels, or the native step (built for x86-64-v3)")
    parser.add_argument("--native", action="store_true", help="time the segments natively instead")
    parser.add_argument("--repeat", type=int, default=3, help="native: best of this many")
    parser.add_argument("--annotate", action="store_true", help="print callgrind's top functions of the step")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    os.environ.setdefault("TI_CPU_MAX_NUM_THREADS", "1")
    if args.schedule == "native":
        os.environ.setdefault("FREEFORM_NATIVE_ARCH", "x86-64-v3")  # (what valgrind runs: AVX2 + FMA)
        os.environ.setdefault("FREEFORM_FAST_MATH", "1")  # (the native step's path)
    if args.native:
        values = measure(args, None)
        report(values, "ns", 1e9, args)
        return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not args.child:
            cmd = ["valgrind", "--tool=callgrind", "--instr-atstart=no",
                   f"--callgrind-out-file={tmp}/cg.out", sys.executable, __file__, "--child",
                   *sys.argv[1:]]
            env = {**os.environ, "PROFILE_SIM_OUT": str(tmp), "PROFILE_SIM_ANNOTATE": "1" if args.annotate else ""}
            subprocess.run(cmd, env=env, check=True)
            return
        cg = callgrind_shim(tmp)
        if not cg.cg_running():
            raise SystemExit("--child runs under valgrind only")
        values = measure(args, cg)
        report(values, "instructions", 1.0, args)


if __name__ == "__main__":
    main()
