"""The two schedules that drive one physics: which thread runs which link, voxel and robot, and when.

One step = every link's ``link_update`` (links.py), then every voxel's ``voxel_update`` (voxels.py), then every
robot's ``robot_advance`` (clock.py) and, when its step count reaches a trace sample, ``summarise_robot``
(summaries.py). Both schedules call these same functions:

* ``flat`` (the CUDA default, "soa" arrays): one thread per link, then per voxel, then per robot, ``UNROLL``
  steps per launch.
* ``robots`` (the CPU default, "aos" arrays): each robot is run by a *block* of ``B`` lanes that stride over its
  links, then its voxels, then (lane 0) its bookkeeping, with a barrier between the phases and the step loop
  inside the kernel. On the CPU ``B`` = 1 and the barrier is compiled out: one worker per CPU thread takes the next
  unclaimed robot from an atomic queue and runs it many steps (no per-step thread-pool synchronisation, which would
  cost more than a step of a small robot; the robot's data stays in cache; robots of any size balance
  dynamically). On CUDA (``simt``; "auto" picks it for small robots: ``resolve_schedule``) the block is a thread
  block of ``B`` threads ("soa" arrays: neighbouring lanes read neighbouring links), ``ti.simt.block.sync()``
  between the phases, one launch for a whole ``advance`` or control period. A CPU block of ``B`` > 1 runs its lanes
  one after another within each phase: the GPU's partition of the work, testable on the CPU (``block_dims``).

Every kernel takes the three buffers of ``state.BUFFERS`` and a step count; loops are bounded by the batch's counts
in the buffers' header, not by the buffers' sizes: the Engine reuses buffers sized for the largest batch seen, whose
tails hold stale items.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
import os
import warnings
from types import SimpleNamespace

from freeform.sim import native
from freeform.sim.access import make_access, make_numbers
from freeform.sim.clock import make_clock
from freeform.sim.config import SCHEDULES
from freeform.sim.links import make_links
from freeform.sim.quat import make_quat
from freeform.sim.runtime import ti
from freeform.sim.sensing import make_sensing
from freeform.sim.state import BUFFERS, HDR, LI, RI, RT, RUNNING, VI, VR, Switches
from freeform.sim.summaries import make_summaries
from freeform.sim.voxels import make_voxels

# the memory order each schedule reads best (access.py); "native" steps the robots schedule's buffers in C++
# (native.py)
ORDER_OF = {"robots": "aos", "flat": "soa", "native": "aos"}
UNROLL = 2  # steps per launch of the flat schedule
# run_flat's arguments by name, in order: what a compute graph binds (flat_graph; Engine.advance)
FLAT_ARGS = (*BUFFERS, "n_steps")
# a control step's (control_robots; control_graph binds them by name): the commands (f64 [n]), the sensing array
# (f64, sensing.py), the period (s), the ramp (s), whether the period starts at the robot's clock (1) or at its last
# limit (0), the steps (at least the furthest-behind robot's)
COMMAND_ARGS = (*BUFFERS, "commands", "period", "ramp", "from_clock")
CONTROL_ARGS = (*BUFFERS, "commands", "out", "period", "ramp", "from_clock", "n_steps")
# The flat schedule's host cost is per launch (Python, argument marshalling): runs of this many launches go through
# one compute graph (Taichi's ti.graph, dispatched from C++) where the backend has one; SimConfig.graph_launches.
# Taichi 1.7's CPU backend splits a range-for with a runtime bound into one block per thread of at least this
# many iterations (see run_robots); only the CPU schedule's thread count depends on it, never the results.
CPU_MIN_TASK_ITEMS = 512


# The robots schedule on CUDA (a thread block per robot) against flat, measured on one H100 (docs/physics.md, "The
# GPU"; benchmarks/bench_blocks.py): faster for the design env's bodies at every batch (µs a step 8.7 vs 34.8 at 1
# body, 13.2 vs 34.5 at 128 with B = 256, 38.1 vs 48.0 at 1,024 with B = 128; the paper epoch's simulation 1.34
# vs 3.53 s), even at 8³ cubes (1,344 links: 29.6 vs 30.0), slower beyond (12³: 81.6 vs 33.6; 20³: 433.7 vs 45.1).
# "auto" picks it on CUDA for batches whose largest robot has at most CUDA_AUTO_MAX_LINKS links.
# $FREEFORM_CUDA_ROBOTS: "0" keeps "auto" flat on CUDA; a number fixes B (a multiple of 32, at most 1024); "1" or
# "auto" (or unset): B chosen per batch (``block_dim_for``).
CUDA_ROBOTS_ENV = "FREEFORM_CUDA_ROBOTS"
CUDA_AUTO_MAX_LINKS = 1024
# B on CUDA: the smallest of these that leaves each lane at most LINKS_PER_LANE links of the batch's largest robot,
# but no more lanes in all than CUDA_BATCH_LANES (a big batch fills the GPU with its blocks: at 1,024 design bodies
# B = 128 beat 256 and 512, at 128 bodies B = 256 beat 128 and 512). A warp at least (the barrier's unit); robots of
# very different sizes share one launch's B: a small robot's block idles some lanes, a large one's lanes take more
# links each.
CUDA_BLOCK_DIMS = (32, 64, 128, 256, 512)
LINKS_PER_LANE = 2
CUDA_BATCH_LANES = 1 << 17


def cuda_robots_flag() -> str:
    """``$FREEFORM_CUDA_ROBOTS``, checked: "" (unset), "0", "1", "auto" or a B."""
    flag = os.environ.get(CUDA_ROBOTS_ENV, "")
    if flag not in ("", "0", "1", "auto") and not (flag.isdigit() and int(flag) % 32 == 0 and 32 <= int(flag) <= 1024):
        raise ValueError(f"{CUDA_ROBOTS_ENV} must be 0, 1, auto or a multiple of 32 up to 1024, got {flag!r}")
    return flag


def block_dim_for(max_links: int, num_robots: int = 1) -> int:
    """The robots schedule's B on CUDA for a batch of ``num_robots`` whose largest has ``max_links`` links (or the B
    that ``$FREEFORM_CUDA_ROBOTS`` names): the smallest of ``CUDA_BLOCK_DIMS`` giving each lane at most
    ``LINKS_PER_LANE`` links, the largest otherwise, then halved while the batch's lanes pass ``CUDA_BATCH_LANES``."""
    flag = cuda_robots_flag()
    if flag.isdigit() and flag not in ("0", "1"):
        return int(flag)
    b = next((b for b in CUDA_BLOCK_DIMS if max_links <= b * LINKS_PER_LANE), CUDA_BLOCK_DIMS[-1])
    while b > CUDA_BLOCK_DIMS[0] and b * num_robots > CUDA_BATCH_LANES:
        b //= 2
    return b


def resolve_schedule(schedule: str, arch: str, max_links: int | None = None, precision: str | None = None,
                     switches: Switches | None = None) -> str:
    """The schedule to run on ``arch`` ("cpu" | "cuda"), the one place that decides it. "auto" on the CPU: "native"
    for a batch it runs (``precision`` and ``switches``, ``state.Switches``, given: a batch is known) where it is
    measured faster than Taichi's step for the instruction set it is built for and a compiler built it
    (``native.usable``), else "robots". On CUDA "robots" (a thread block per robot) when the batch's largest robot
    has at most ``CUDA_AUTO_MAX_LINKS`` links (``max_links``; None: not known yet, as for a Simulator before its
    first batch) and ``$FREEFORM_CUDA_ROBOTS`` is not "0", else "flat". "native" for a batch it does not run is
    refused naming the setting (``native.unsupported``); for one it runs, compiled now (not at the first step)."""
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    if arch not in ("cpu", "cuda"):
        raise ValueError(f"arch must be 'cpu' or 'cuda' here (the arch Taichi runs on), got {arch!r}")
    flag = cuda_robots_flag() if arch == "cuda" else ""
    if schedule == "native" and arch != "cpu":
        raise ValueError(f"schedule='native' is the CPU's (a C++ step on host memory), not {arch!r}'s: use 'auto'")
    batch = switches is not None
    if schedule == "native" and batch:  # (refused, or compiled, before anything of the batch is built)
        if (why := native.unsupported(precision, switches)) is not None:
            raise ValueError(f"schedule='native' does not run {why}: use schedule='robots' (docs/physics.md, "
                             "\"The native schedule\")")
        native.library()
    if schedule != "auto":
        return schedule
    if arch == "cpu":
        return "native" if batch and native.usable(precision, switches) else "robots"
    small = max_links is not None and max_links <= CUDA_AUTO_MAX_LINKS
    return "robots" if small and flag != "0" else "flat"


VOXELYZE_FLAT_FLOOR = Switches(floor=1, terrain=0, rl4design=0, dynamic_dt=0)  # the default simulation


@functools.cache
def make_kernels(precision: str, order: str = "soa", switches: Switches = VOXELYZE_FLAT_FLOOR, block_dim: int = 1,
                 simt: bool = False) -> SimpleNamespace:
    """Compile-once kernels for "f32" | "f64", memory order "soa" | "aos" and the compile-time ``switches``
    (``state.Switches``: each combination used compiles once), the robots schedule's block of ``block_dim`` lanes
    per robot, and ``simt``: each lane a GPU thread, a barrier between the phases (CUDA only), or else one CPU
    thread running the lanes in turn (``block_dim`` 1 and no ``simt``: the CPU's robots schedule): ``run_robots``,
    ``run_flat``, ``flat_graph``, the
    control step's ``command``, ``control_robots`` and ``control_graph`` (``Engine.control_step``), and the test
    hook ``probe_rotations``. Every kernel takes the three buffers (``state.BUFFERS``) and a step count;
    the switches are baked in rather than passed as ``ti.template`` arguments, so every argument is an array or a
    number (what a compute graph can bind)."""
    acc = make_access(precision, order)
    ld, st, header, bind, Buffer = acc.ld, acc.st, acc.header, acc.bind, acc.Buffer
    link_update = make_links(precision, order).link_update
    voxel_update = make_voxels(precision, order).voxel_update
    robot_advance = make_clock(precision, order).robot_advance
    summarise_robot = make_summaries(precision, order).summarise_robot
    sensing = make_sensing(precision, order)
    real = make_numbers(precision).real
    Reals, Ints, F64s = Buffer["reals"], Buffer["ints"], Buffer["f64s"]
    Commands = ti.types.ndarray(dtype=ti.f64, ndim=1)

    @ti.func
    def trace_sample(r, s: ti.template()):
        """After robot r's step: frame n / k of the trace once it has run n steps, n a multiple of k (the header's
        TRACE_STEPS; 0: no trace). Only a step that ran calls it, so a robot that stopped leaves its later frames
        alone."""
        every = s.h[HDR.TRACE_STEPS]
        if every > 0:
            n = ld(s.ri, RI.STEP, r)
            if n % every == 0 and n // every < s.h[HDR.TRACE_FRAMES]:  # (sized for the step cap: a guard only)
                summarise_robot(r, s, n // every)

    @ti.func
    def stepping(r, s: ti.template()):
        """Robot r takes the coming step: it is running and its clock has not passed its limit (``RT.UNTIL``)."""
        return ld(s.ri, RI.STATUS, r) == RUNNING and ld(s.rt, RT.T, r) < ld(s.rt, RT.UNTIL, r)

    B = block_dim
    if B < 1 or (simt and B % 32):
        raise ValueError(f"block_dim must be >= 1 (a multiple of 32 with simt), got {B}")
    loop_block = B if simt else None  # ti.loop_config: the thread block of a robot (CUDA only)

    @ti.func
    def barrier():
        """Every lane of the block waits here for the others (CUDA's ``__syncthreads``); compiled out on the CPU,
        where one thread runs the block's lanes in turn within each phase."""
        if ti.static(simt):
            ti.simt.block.sync()

    @ti.func
    def lanes(lo, hi, lane, update: ti.template(), r, s: ti.template()):
        """``update(i, r, s)`` of robot r's items ``lo`` … ``hi − 1`` by lane ``lane`` of a block of B: its items
        are lane, lane + B, … (neighbouring lanes, neighbouring items); on the CPU one thread runs every lane in
        turn. Items within a phase are independent (each writes its own columns), so the partition leaves the bits
        as they were."""
        if ti.static(B == 1):
            for i in range(lo, hi):
                update(i, r, s)
        elif ti.static(simt):
            for k in range((hi - lo - lane + B - 1) // B):
                update(lo + lane + k * B, r, s)
        else:
            for ln in range(B):
                for k in range((hi - lo - ln + B - 1) // B):
                    update(lo + ln + k * B, r, s)

    @ti.func
    def robot_voxel_update(v, r, s: ti.template()):
        """``voxel_update`` in ``lanes``' form (a voxel finds its robot itself)."""
        voxel_update(v, s)

    @ti.func
    def robot_steps(r, lane, n_steps, s: ti.template()):
        """``n_steps`` steps of robot r by lane ``lane`` of its block: the links, then the voxels, then (lane 0) the
        robot's clock and trace, a barrier after each phase and after each read of the status that a later phase
        may write (a link or a voxel marks its robot diverged), so every lane of the block takes the same branches.
        Lane 0's serial loops over the robot (rl4design's ω² max, the trace's sums) are the block's reductions, in
        a fixed order: no float atomics, the same bits on every run. With B = 1 and no barrier: one thread's
        ``if stepping: links; if running: voxels; if running: clock`` per step, as the schedule always was."""
        for _ in range(n_steps):
            go = stepping(r, s)
            barrier()
            if go:
                lanes(ld(s.ri, RI.LSTART, r), ld(s.ri, RI.LEND, r), lane, link_update, r, s)
            barrier()
            go = go and ld(s.ri, RI.STATUS, r) == RUNNING  # a diverged link aborts the step, as in VX
            barrier()
            if go:
                lanes(ld(s.ri, RI.VSTART, r), ld(s.ri, RI.VEND, r), lane, robot_voxel_update, r, s)
            barrier()
            if lane == 0 and go and ld(s.ri, RI.STATUS, r) == RUNNING:
                robot_advance(r, s)
                trace_sample(r, s)
            barrier()

    @ti.func
    def robots_worker(t, reals: ti.template(), ints: ti.template(), f64s: ti.template(), n_steps):
        """Iteration t of the robots schedule's range. CUDA (``simt``): lane t % B of robot t // B's block, each
        robot one thread block (the GPU's block scheduler balances robots of different sizes).

        CPU: Taichi's CPU backend splits a range-for into blocks of at least ``CPU_MIN_TASK_ITEMS`` iterations, one
        per thread: the loop runs ``workers`` such blocks, only the first iteration of each does anything, so
        each thread runs one block of a virtual range, and the robots are handed out through an atomic counter
        (reset to 0 by a top-level statement before the loop: it runs first, as a serial task); each is run
        ``n_steps`` steps before the thread takes the next."""
        if ti.static(simt):
            h = header(ints)
            robot_steps(t // B, t % B, n_steps, bind(reals, ints, f64s, h, switches))
        elif t % CPU_MIN_TASK_ITEMS == 0:
            h = header(ints)
            r = ti.atomic_add(ints[HDR.QUEUE], 1)
            while r < h[HDR.N_ROBOTS]:
                robot_steps(r, 0, n_steps, bind(reals, ints, f64s, h, switches))
                r = ti.atomic_add(ints[HDR.QUEUE], 1)

    @ti.func
    def robots_range(ints: ti.template(), workers):
        """The robots schedule's range: B lanes per robot on CUDA, ``workers`` blocks of the CPU's minimum task."""
        n = workers * CPU_MIN_TASK_ITEMS
        if ti.static(simt):
            n = ints[HDR.N_ROBOTS] * B
        return n

    @ti.kernel
    def run_robots(reals: Reals, ints: Ints, f64s: F64s, n_steps: ti.i32, workers: ti.i32):
        """Every robot ``n_steps`` steps (robots_worker): on the CPU ``workers`` threads each take the next
        unclaimed robot; on CUDA one thread block per robot."""
        if ti.static(not simt):
            ints[HDR.QUEUE] = 0
        ti.loop_config(block_dim=loop_block)
        for t in range(robots_range(ints, workers)):
            robots_worker(t, reals, ints, f64s, n_steps)

    # ------------------------------------------------------------ a control step (Engine.control_step)
    @ti.func
    def command_voxel(v, s: ti.template(), commands: ti.template(), ramp):
        """Voxel v's new command (what ``Engine.set_commands`` writes): with a ramp, the command in effect so far
        becomes the ramp's start."""
        if ramp > 0.0:
            st(s.vr, VR.CMD0, v, ld(s.vr, VR.CMD, v))
        st(s.vr, VR.CMD, v, ti.cast(commands[v], real))

    @ti.func
    def command_robot(r, s: ti.template(), period, ramp, from_clock):
        """Robot r's next clock limit, ``period`` after its last one (or after its clock, the first time: what
        ``Engine.advance_time`` writes), and its ramp's length."""
        start = ld(s.rt, RT.UNTIL, r)
        if from_clock != 0:
            start = ld(s.rt, RT.T, r)
        st(s.rt, RT.UNTIL, r, start + period)
        st(s.rt, RT.RAMP, r, ramp)

    @ti.kernel
    def command(reals: Reals, ints: Ints, f64s: F64s, commands: Commands, period: ti.f64, ramp: ti.f64,
                from_clock: ti.i32):
        """A control step's start: every voxel's command, every robot's limit and ramp."""
        for v in range(ints[HDR.N_VOXELS]):
            h = header(ints)
            command_voxel(v, bind(reals, ints, f64s, h, switches), commands, ramp)
        for r in range(ints[HDR.N_ROBOTS]):
            h = header(ints)
            command_robot(r, bind(reals, ints, f64s, h, switches), period, ramp, from_clock)

    @ti.kernel
    def control_robots(reals: Reals, ints: Ints, f64s: F64s, commands: Commands, out: sensing.Out, period: ti.f64,
                       ramp: ti.f64, from_clock: ti.i32, n_steps: ti.i32, workers: ti.i32):
        """A whole control step in one launch of the robots schedule: the commands written, ``n_steps`` steps
        of every robot (each idles once its clock passes its limit), the senses read (sensing.py). Its loops run in
        order, each a parallel task; they repeat ``command``'s and ``sense``'s because Taichi runs in parallel only
        the loops a kernel itself holds at its top level."""
        for v in range(ints[HDR.N_VOXELS]):
            h = header(ints)
            command_voxel(v, bind(reals, ints, f64s, h, switches), commands, ramp)
        for r in range(ints[HDR.N_ROBOTS]):
            h = header(ints)
            command_robot(r, bind(reals, ints, f64s, h, switches), period, ramp, from_clock)
        if ti.static(not simt):
            ints[HDR.QUEUE] = 0
        ti.loop_config(block_dim=loop_block)
        for t in range(robots_range(ints, workers)):
            robots_worker(t, reals, ints, f64s, n_steps)
        for r in range(ints[HDR.N_ROBOTS]):
            h = header(ints)
            sensing.sense_robot(r, bind(reals, ints, f64s, h, switches), out)
        for v in range(ints[HDR.N_VOXELS]):
            h = header(ints)
            sensing.sense_voxel(v, bind(reals, ints, f64s, h, switches), out)

    @ti.func
    def link_phase(lk, s: ti.template()):
        r = ld(s.vi, VI.ROBOT, ld(s.li, LI.NEG, lk))
        if stepping(r, s):
            link_update(lk, r, s)

    @ti.func
    def voxel_phase(v, s: ti.template()):
        if stepping(ld(s.vi, VI.ROBOT, v), s):
            voxel_update(v, s)

    @ti.func
    def robot_phase(r, s: ti.template()):
        if stepping(r, s):
            robot_advance(r, s)
            trace_sample(r, s)

    @ti.kernel
    def run_flat(reals: Reals, ints: Ints, f64s: F64s, n_steps: ti.i32):
        """One thread per link, then per voxel, then per robot; ``min(n_steps, UNROLL)`` steps per launch. Each
        thread loads the header (a few cached words) rather than the host passing every region's place."""
        for k in ti.static(range(UNROLL)):
            for lk in range(ints[HDR.N_LINKS]):
                h = header(ints)  # (a variable: passed as an expression it would be loaded again at every use)
                if k < n_steps:
                    link_phase(lk, bind(reals, ints, f64s, h, switches))
            for v in range(ints[HDR.N_VOXELS]):
                h = header(ints)  # (a variable: passed as an expression it would be loaded again at every use)
                if k < n_steps:
                    voxel_phase(v, bind(reals, ints, f64s, h, switches))
            for r in range(ints[HDR.N_ROBOTS]):
                h = header(ints)  # (a variable: passed as an expression it would be loaded again at every use)
                if k < n_steps:
                    robot_phase(r, bind(reals, ints, f64s, h, switches))

    def flat_graph(launches: int):
        """A compute graph of ``launches`` ``run_flat`` launches of ``UNROLL`` steps each, its arrays and counts
        bound when it runs (``graph.run({name: value})``, the names of ``run_flat``'s arguments): the launches are
        issued from C++, without Python's per-launch cost. None where the backend has no compute graphs
        (quadrants) or ``launches`` is 0; built once per kernel variant and length."""
        return _graph(False, launches) if launches else None

    def control_graph(launches: int):
        """A compute graph of one control step on the flat schedule, bound by ``CONTROL_ARGS``' names: ``command``,
        ``launches`` launches of ``run_flat`` (``n_steps`` each, at most ``UNROLL``), ``sense``. None where the
        backend has no compute graphs; built once per kernel variant and length."""
        return _graph(True, launches)

    def _graph(control: bool, launches: int):
        """The graph of ``launches`` ``run_flat`` launches, between ``command`` and ``sense`` for a control step,
        built on first use; None (said once) where the backend has none or building it fails."""
        key = (control, launches)
        if key not in graphs:
            graphs[key] = None
            if hasattr(ti.graph, "GraphBuilder"):
                try:
                    args = _graph_args(CONTROL_ARGS if control else FLAT_ARGS)
                    builder = ti.graph.GraphBuilder()
                    if control:
                        builder.dispatch(command, *(args[name] for name in COMMAND_ARGS))
                    for _ in range(launches):
                        builder.dispatch(run_flat, *(args[name] for name in FLAT_ARGS))
                    if control:
                        builder.dispatch(sensing.sense, *(args[name] for name in (*BUFFERS, "out")))
                    graphs[key] = builder.compile()
                except Exception as exc:  # a backend or arch whose graphs fail: launch from Python, say so once
                    warnings.warn(f"freeform.sim: no compute graph for the flat schedule ({type(exc).__name__}: "
                                  f"{exc}); launching from Python", RuntimeWarning, stacklevel=3)
        return graphs[key]

    def _graph_args(names):
        """The graph's placeholders for the arguments ``names``, by name."""
        scalars = {"period": ti.f64, "ramp": ti.f64, "from_clock": ti.i32, "n_steps": ti.i32}
        return {name: acc.graph_arg(name) if name in BUFFERS
                else ti.graph.Arg(ti.graph.ArgKind.SCALAR, name, dtype=scalars[name]) if name in scalars
                else ti.graph.Arg(ti.graph.ArgKind.NDARRAY, name, dtype=ti.f64, ndim=1)  # commands, out
                for name in names}

    graphs: dict = {}
    return SimpleNamespace(run_robots=run_robots, run_flat=run_flat, flat_graph=flat_graph, command=command,
                           control_robots=control_robots, control_graph=control_graph, sense=sensing.sense,
                           probe_rotations=make_quat(precision).probe_rotations, precision=precision, order=order,
                           switches=switches, block_dim=block_dim, simt=simt)
