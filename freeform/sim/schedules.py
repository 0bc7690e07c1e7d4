"""The two schedules that drive one physics: which thread runs which link, voxel and robot, and when.

One step = every link's ``link_update`` (links.py), then every voxel's ``voxel_update`` (voxels.py), then every
robot's ``robot_advance`` (clock.py) and, when its step count reaches a trace sample, ``summarise_robot``
(summaries.py). Both schedules call these same functions:

* ``flat`` (the CUDA default, "soa" arrays): one thread per link, then per voxel, then per robot, ``UNROLL``
  steps per launch.
* ``robots`` (the CPU default, "aos" arrays): one worker per CPU thread; each takes the next unclaimed robot from an
  atomic queue and runs it many steps (no per-step thread-pool synchronisation, which would cost more than a step
  of a small robot; the robot's data stays in cache; robots of any size balance dynamically). On a GPU it would
  run one thread per robot, so it is refused there (``resolve_schedule``).

Loops are bounded by the batch's counts, passed as arguments, not by the arrays' shapes: the Engine reuses arrays
sized for the largest batch seen, whose tail holds stale items.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
import warnings
from types import SimpleNamespace

from freeform.sim.access import make_access, make_numbers
from freeform.sim.clock import make_clock
from freeform.sim.links import make_links
from freeform.sim.quat import make_quat
from freeform.sim.runtime import ti
from freeform.sim.state import LI, LR, LT, MT, RI, RT, RUNNING, TABLES, VI, VR, Switches
from freeform.sim.summaries import make_summaries
from freeform.sim.voxels import make_voxels

SCHEDULES = ("auto", "robots", "flat")
# the memory order each schedule reads best (access.py)
ORDER_OF = {"robots": "aos", "flat": "soa"}
UNROLL = 2  # steps per launch of the flat schedule
# run_flat's arguments by name, in order: what a compute graph binds (flat_graph; Engine.advance)
FLAT_ARGS = (*TABLES, "gp", "hf", "tr", "trace_steps", "n_voxels", "n_links", "n_robots", "n_steps")
# The flat schedule's host cost is per launch (Python, argument marshalling): runs of this many launches go through
# one compute graph (Taichi's ti.graph, dispatched from C++) where the backend has one; SimConfig.graph_launches.
# Taichi 1.7's CPU backend splits a range-for with a runtime bound into one block per thread of at least this
# many iterations (see run_robots); only the CPU schedule's thread count depends on it, never the results.
CPU_MIN_TASK_ITEMS = 512


def resolve_schedule(schedule: str, arch: str) -> str:
    """The schedule to run on ``arch`` ("cpu" | "cuda"): "auto" picks "flat" on CUDA and "robots" on the CPU.

    "robots" on CUDA is refused: it would run one GPU thread per robot (128 threads for a paper batch)."""
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    if arch not in ("cpu", "cuda"):
        raise ValueError(f"arch must be 'cpu' or 'cuda' here (the arch Taichi runs on), got {arch!r}")
    if schedule == "auto":
        return "flat" if arch == "cuda" else "robots"
    if schedule == "robots" and arch == "cuda":
        raise ValueError("schedule='robots' runs one GPU thread per robot and is refused on CUDA; "
                         "use schedule='flat' (or 'auto', which picks it there)")
    return schedule


VOXELYZE_FLAT_FLOOR = Switches(floor=1, terrain=0, rl4design=0, dynamic_dt=0)  # the default simulation


@functools.cache
def make_kernels(precision: str, order: str = "soa", switches: Switches = VOXELYZE_FLAT_FLOOR) -> SimpleNamespace:
    """Compile-once kernels for "f32" | "f64", memory order "soa" | "aos" and the compile-time ``switches``
    (``state.Switches``: each combination used compiles once): ``run_robots``, ``run_flat`` and the test hook
    ``probe_rotations``. The switches are baked into the kernels rather than passed as ``ti.template`` arguments,
    so every kernel argument is an array or a number (what a compute graph can bind: ``FlatLauncher``)."""
    sw = switches
    acc = make_access(precision, order)
    num = make_numbers(precision)
    ld = acc.ld
    link_update = make_links(precision, order).link_update
    voxel_update = make_voxels(precision, order).voxel_update
    robot_advance = make_clock(precision, order).robot_advance
    summaries = make_summaries(precision, order)
    summarise_robot, TraceArr = summaries.summarise_robot, summaries.TraceArr
    VrArr, ViArr, LrArr, LiArr = acc.arg(VR), acc.arg(VI), acc.arg(LR), acc.arg(LI)
    RtArr, RiArr, MtArr, LtArr = acc.arg(RT), acc.arg(RI), acc.arg(MT), acc.arg(LT)
    GpArr = ti.types.ndarray(dtype=ti.f64, ndim=1)  # the GP vector
    HfArr = ti.types.ndarray(dtype=num.real, ndim=1)  # the terrain's height grid

    @ti.func
    def trace_sample(r, vr: ti.template(), vi: ti.template(), rt: ti.template(), ri: ti.template(),
                     mt: ti.template(), tr: ti.template(), trace_steps):
        """After robot r's step: frame s / k of the trace once it has run s steps, s a multiple of k = trace_steps
        (0: no trace). Only a step that ran calls it, so a robot that stopped leaves its later frames alone."""
        if trace_steps > 0:
            s = ld(ri, RI.STEP, r)
            if s % trace_steps == 0 and s // trace_steps < tr.shape[0]:  # (sized for the step cap: a guard only)
                summarise_robot(r, vr, vi, rt, ri, mt, tr, s // trace_steps)

    @ti.func
    def robot_step(r, vr: ti.template(), vi: ti.template(), lr: ti.template(), li: ti.template(),
                   rt: ti.template(), ri: ti.template(), mt: ti.template(), lt: ti.template(), gp: ti.template(),
                   hf: ti.template(), tr: ti.template(), trace_steps):
        """One step of robot r by the calling thread alone."""
        if ld(ri, RI.STATUS, r) == RUNNING:
            for lk in range(ld(ri, RI.LSTART, r), ld(ri, RI.LEND, r)):
                link_update(lk, vr, vi, lr, li, rt, ri, mt, lt, gp, sw)
            if ld(ri, RI.STATUS, r) == RUNNING:  # a diverged link aborts the step, as in VX
                for v in range(ld(ri, RI.VSTART, r), ld(ri, RI.VEND, r)):
                    voxel_update(v, vr, vi, lr, li, rt, ri, mt, lt, gp, hf, sw)
            if ld(ri, RI.STATUS, r) == RUNNING:
                robot_advance(r, lr, rt, ri, gp, sw)
                trace_sample(r, vr, vi, rt, ri, mt, tr, trace_steps)

    @ti.kernel
    def run_robots(vr: VrArr, vi: ViArr, lr: LrArr, li: LiArr, rt: RtArr, ri: RiArr, mt: MtArr,
                   lt: LtArr, gp: GpArr, hf: HfArr, tr: TraceArr, trace_steps: ti.i32, n_robots: ti.i32,
                   n_steps: ti.i32, queue: ti.types.ndarray(dtype=ti.i32, ndim=1), workers: ti.i32):
        """``workers`` threads each take the next unclaimed robot (of ``n_robots``) from ``queue`` and run it
        ``n_steps`` steps, until none is left.

        Why not ``for r in range(R)``: Taichi's CPU backend gives each thread a block of at least
        ``CPU_MIN_TASK_ITEMS`` iterations of a range-for with a runtime bound (``loop_config(block_dim)`` is not
        honoured there), so a batch of fewer robots than that would run on one thread. Each worker therefore owns
        one such block of a virtual range, and the robots are handed out through an atomic counter.
        """
        queue[0] = 0  # (a top-level statement: runs before the parallel loop, as a serial task)
        for t in range(workers * CPU_MIN_TASK_ITEMS):
            if t % CPU_MIN_TASK_ITEMS == 0:
                r = ti.atomic_add(queue[0], 1)
                while r < n_robots:
                    for _ in range(n_steps):
                        robot_step(r, vr, vi, lr, li, rt, ri, mt, lt, gp, hf, tr, trace_steps)
                    r = ti.atomic_add(queue[0], 1)

    @ti.kernel
    def run_flat(vr: VrArr, vi: ViArr, lr: LrArr, li: LiArr, rt: RtArr, ri: RiArr, mt: MtArr,
                 lt: LtArr, gp: GpArr, hf: HfArr, tr: TraceArr, trace_steps: ti.i32, n_voxels: ti.i32,
                 n_links: ti.i32, n_robots: ti.i32, n_steps: ti.i32):
        """One thread per link, then per voxel, then per robot; ``min(n_steps, UNROLL)`` steps per launch."""
        for s in ti.static(range(UNROLL)):
            for lk in range(n_links):
                if s < n_steps and ld(ri, RI.STATUS, ld(vi, VI.ROBOT, ld(li, LI.NEG, lk))) == RUNNING:
                    link_update(lk, vr, vi, lr, li, rt, ri, mt, lt, gp, sw)
            for v in range(n_voxels):
                if s < n_steps and ld(ri, RI.STATUS, ld(vi, VI.ROBOT, v)) == RUNNING:
                    voxel_update(v, vr, vi, lr, li, rt, ri, mt, lt, gp, hf, sw)
            for r in range(n_robots):
                if s < n_steps and ld(ri, RI.STATUS, r) == RUNNING:
                    robot_advance(r, lr, rt, ri, gp, sw)
                    trace_sample(r, vr, vi, rt, ri, mt, tr, trace_steps)

    def flat_graph(launches: int):
        """A compute graph of ``launches`` ``run_flat`` launches of ``UNROLL`` steps each, its arrays and counts
        bound when it runs (``graph.run({name: value})``, the names of ``run_flat``'s arguments): the launches are
        issued from C++, without Python's per-launch cost. None where the backend has no compute graphs
        (quadrants) or ``launches`` is 0; built once per kernel variant and length."""
        key = ("flat", launches)
        if key not in graphs:
            graphs[key] = None
            if launches and hasattr(ti.graph, "GraphBuilder"):
                try:
                    graphs[key] = _build_flat_graph(launches)
                except Exception as exc:  # a backend or arch whose graphs fail: launch from Python, say so once
                    warnings.warn(f"freeform.sim: no compute graph for the flat schedule ({type(exc).__name__}: "
                                  f"{exc}); launching from Python", RuntimeWarning, stacklevel=3)
        return graphs[key]

    def _build_flat_graph(launches: int):
        nd, scalar = ti.graph.ArgKind.NDARRAY, ti.graph.ArgKind.SCALAR
        other = {"gp": ti.graph.Arg(nd, "gp", dtype=ti.f64, ndim=1), "hf": ti.graph.Arg(nd, "hf", dtype=num.real, ndim=1),
                 "tr": ti.graph.Arg(nd, "tr", dtype=ti.f64, ndim=3)}
        args = [acc.graph_arg(TABLES[name], name) if name in TABLES else
                other.get(name) or ti.graph.Arg(scalar, name, dtype=ti.i32) for name in FLAT_ARGS]
        builder = ti.graph.GraphBuilder()
        for _ in range(launches):
            builder.dispatch(run_flat, *args)
        return builder.compile()

    graphs: dict = {}
    return SimpleNamespace(run_robots=run_robots, run_flat=run_flat, flat_graph=flat_graph,
                           probe_rotations=make_quat(precision).probe_rotations, precision=precision, order=order,
                           switches=switches)
