"""The low-level engine: one batch's state in Taichi ndarrays, advanced step by step.

``Simulator`` builds on this; tests and tools use it directly for what the public API does not expose —
fixed voxels, initial velocities and constant temperatures (all on the ``Layout``), per-step traces,
link strains. Nothing here loops over voxels in Python.

The arrays' columns are declared in ``state.py``; the Engine fills them by name. The device arrays themselves live in
a ``DeviceArrays`` that outlives the Engine: a ``Simulator`` keeps one and every batch reuses it, grown only when a
batch outgrows it, so a long training run stops allocating device memory once its largest batch has been seen
(Taichi's CUDA pool splits blocks and never merges them: fresh arrays every epoch fragment it).
"""

from __future__ import annotations

import math

import numpy as np

from freeform.sim import runtime
from freeform.sim.config import SimConfig, material_table
from freeform.sim.initial import initial_state, recommended_dt
from freeform.sim.layout import Layout
from freeform.sim.schedules import FLAT_ARGS, ORDER_OF, SCHEDULES, UNROLL, make_kernels, resolve_schedule
from freeform.sim.state import (  # noqa: F401  (re-exported for tools and tests)
    DIVERGED,
    DONE,
    EV_END,
    EV_SAMPLE,
    EV_START,
    FIXED,
    GP,
    LI,
    LR,
    LT,
    MT,
    RI,
    RT,
    RUNNING,
    SMALL,
    STALLED,
    STATIC,
    SUMMARY,
    TABLES,
    VI,
    VR,
    Switches,
    Table,
)
from freeform.sim.summaries import make_summaries

__all__ = ["SCHEDULES", "DeviceArrays", "Engine", "recommended_dt"]

# A batch that outgrows the arrays gets this much room beyond its own size, so a run whose bodies grow slowly
# reallocates a logarithmic number of times, not every epoch.
CAPACITY_HEADROOM = 1.25
INT32_MAX = np.iinfo(np.int32).max


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


class DeviceArrays:
    """Device arrays kept across Engines: one per state table, precision and memory order, each grown to the
    largest batch seen (plus ``CAPACITY_HEADROOM``) and never shrunk; items past a batch's own are stale and
    never read (the kernels' loops are bounded by the batch's counts).

    One Engine uses them at a time: building an Engine claims them, and an older Engine on the same arrays refuses
    to run or read (its state has been overwritten). ``allocations`` counts the device arrays made.
    """

    def __init__(self) -> None:
        self._arrays: dict[tuple[str, str, str], tuple[object, int]] = {}  # key -> (ndarray, capacity)
        self.allocations = 0
        self.owner: object | None = None

    def table(self, name: str, table: Table, items: int, precision: str, order: str):
        """The ndarray of ``table`` (stored as ``name``) with room for at least ``items`` items in ``order``, made or
        grown as needed: (ndarray, capacity in items)."""
        key = (name, precision, order)
        arr, cap = self._arrays.get(key, (None, 0))
        if arr is None or items > cap:
            cap = max(1, math.ceil(CAPACITY_HEADROOM * items))
            dtype = table.np_dtype(precision)
            if order == "aos":
                arr = runtime.ndarray(dtype, (cap, table.width), rows_as_vectors=True)
            else:
                arr = runtime.ndarray(dtype, (table.width, cap))
            self.allocations += 1
            self._arrays[key] = (arr, cap)
        return arr, cap

    def vector(self, name: str, dtype: np.dtype, length: int):
        """A plain 1-D ndarray of ``length`` values (parameters, counters), made once."""
        key = (name, np.dtype(dtype).name, str(length))
        if key not in self._arrays:
            self._arrays[key] = (runtime.ndarray(np.dtype(dtype), (length,)), length)
            self.allocations += 1
        return self._arrays[key][0]

    def grid(self, name: str, shape: tuple[int, ...]):
        """A float64 ndarray of at least ``shape`` in every dimension (made or grown as needed; kernels index it
        within the batch's own extent), e.g. the trace ``[frames, SUMMARY.width, robots]``."""
        key = (name, "f64", "grid")
        arr, have = self._arrays.get(key, (None, ()))
        if arr is None or len(have) != len(shape) or any(n > h for n, h in zip(shape, have, strict=True)):
            have = tuple(max(n, h) for n, h in zip(shape, have or (0,) * len(shape), strict=True))
            arr = runtime.ndarray(np.dtype(np.float64), have)
            self.allocations += 1
            self._arrays[key] = (arr, have)
        return arr

    def arrays(self) -> dict[tuple[str, str, str], object]:
        """The ndarrays held now, by (name, precision, order) (tests check reuse through object identity)."""
        return {k: a for k, (a, _) in self._arrays.items()}


class Engine:
    """A batch of robots in Taichi ndarrays. ``advance(n)`` runs n steps of every still-running robot.

    schedule: "robots" (one worker per CPU thread taking whole robots from a queue, many steps per launch;
    the CPU default; arrays in "aos" order) or "flat" (one thread per link/voxel/robot; the CUDA default; "soa").
    Both compute the same physics (bit for bit in f64 up to fast-math reassociation, see docs/physics.md).
    arrays: the ``DeviceArrays`` to use (a Simulator passes its own, reused across batches); None = fresh ones.
    """

    def __init__(self, layout: Layout, config: SimConfig, arch: str = "auto", schedule: str = "auto",
                 arrays: DeviceArrays | None = None):
        config.validate()
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
        self.arch = runtime.ensure(arch, config.backend)
        self.schedule = resolve_schedule(schedule, self.arch)
        self.layout, self.config = layout, config
        # one thread per robot walks its own voxels and links: keep each item's columns together ("aos", one
        # voxel = a few cache lines); one thread per item (GPU): neighbouring threads read neighbouring addresses
        self.order = ORDER_OF[self.schedule]
        self.precision = config.precision
        self.np_real = np.float64 if config.precision == "f64" else np.float32
        initial = initial_state(layout, config)
        self.rl4design = initial.switches.rl4design
        self.counts = initial.counts
        self.dt0, self.max_steps = initial.dt0, initial.max_steps
        self.terrain, self.offset, self.switches = initial.terrain, initial.offset, initial.switches
        self.kernels = make_kernels(config.precision, self.order, self.switches)
        host = initial.tables
        R = layout.num_robots
        self._arrays = arrays if arrays is not None else DeviceArrays()
        self._arrays.owner = self
        self._dev = {}
        self._cap = {}
        for name, t in TABLES.items():
            self._dev[name], self._cap[name] = self._arrays.table(name, t, self.counts[t.items], self.precision,
                                                                  self.order)
            self._upload(name, host[name])
        self.gp = self._arrays.vector("gp", np.float64, GP.width)
        runtime.upload(self.gp, initial.globals)
        grid = initial.height_grid
        self.hf = self._arrays.vector("hf", np.dtype(self.np_real), grid.size)  # one per terrain size
        runtime.upload(self.hf, grid.astype(self.np_real))
        # robots schedule: a work counter, and one worker per CPU thread
        self._queue = self._arrays.vector("queue", np.int32, 1)
        self._workers = max(1, min(R, runtime.num_threads()))
        self.steps_done = 0
        # the trace (start_trace): off until asked for; the kernels then take the trace array unread (any size)
        self.trace_steps = 0
        self._trace = self._arrays.grid("trace", (1, SUMMARY.width, 1))

    # ------------------------------------------------------------------ host <-> device, in the kernels' order
    def _check_owner(self) -> None:
        if self._arrays.owner is not self:
            raise RuntimeError(
                "this Engine's device arrays were reused by a later Engine (a Simulator reuses one set of arrays "
                "across batches): read an Engine's results before building the next one from the same Simulator, "
                "or give each live Engine its own Simulator (or Engine(..., arrays=None))")

    def _upload(self, name: str, a: np.ndarray) -> None:
        """Copy host ``a`` (``[columns, items]`` of table ``name``, items ≤ capacity) into its device array."""
        self._check_owner()
        cap = self._cap[name]
        if a.shape[1] < cap:  # the tail is stale on the device anyway; zeros keep uploads a fixed size
            a = np.concatenate([a, np.zeros((a.shape[0], cap - a.shape[1]), dtype=a.dtype)], axis=1)
        runtime.upload(self._dev[name], a.T if self.order == "aos" else a)

    def _download(self, name: str) -> np.ndarray:
        """Host copy ``[columns, capacity]`` of table ``name`` (items past the batch's own are stale)."""
        self._check_owner()
        a = runtime.to_numpy(self._dev[name])
        return a.T if self.order == "aos" else a

    def _table(self, name: str) -> np.ndarray:
        """Host copy ``[columns, items]`` of table ``name``, this batch's items only."""
        return self._download(name)[:, : self.counts[TABLES[name].items]]

    # ------------------------------------------------------------------ stepping
    def advance(self, n_steps: int) -> None:
        """Run ``n_steps`` steps of every robot still running (finished, diverged or stalled robots stay frozen)."""
        self._check_owner()
        if n_steps <= 0 or self.layout.num_robots == 0:
            return
        k, d = self.kernels, self._dev
        args = (*(d[name] for name in TABLES), self.gp, self.hf, self._trace, self.trace_steps)
        n, m, R = self.counts["voxels"], self.counts["links"], self.counts["robots"]
        if self.schedule == "robots":
            k.run_robots(*args, R, n_steps, self._queue, self._workers)
        else:
            left = n_steps
            launches = self.config.graph_launches
            if left >= launches * UNROLL and (graph := k.flat_graph(launches)) is not None:
                bound = dict(zip(FLAT_ARGS, (*args, n, m, R, UNROLL), strict=True))
                while left >= launches * UNROLL:
                    graph.run(bound)
                    left -= launches * UNROLL
            while left > 0:
                k.run_flat(*args, n, m, R, min(left, UNROLL))
                left -= UNROLL
        self.steps_done += n_steps

    def set_velocity(self, velocity: np.ndarray, release_static: bool = True) -> None:
        """Overwrite every voxel's linear velocity (float ``[n, 3]``, m/s), e.g. to launch a settled block.

        release_static: also clear the floor static-friction state (a static voxel ignores its momentum).
        """
        velocity = np.asarray(velocity, dtype=np.float64)
        if velocity.shape != (self.layout.num_voxels, 3):
            raise ValueError(f"velocity must have shape {(self.layout.num_voxels, 3)}, got {velocity.shape}")
        vr = self._table("vr")
        mass = material_table(self.config)[MT.MASS][self.layout.material]
        vr[VR.span("MOM")] = (velocity * mass[:, None]).T
        self._upload("vr", vr)
        if release_static:
            vi = self._table("vi")
            vi[VI.FLAGS] &= ~STATIC
            self._upload("vi", vi)

    # ------------------------------------------------------------------ reading state (host copies)
    def voxel_state(self) -> np.ndarray:
        """float ``[VR.width, n]`` (see ``state.VR`` for the columns)."""
        return self._table("vr")

    def positions(self) -> np.ndarray:
        """Voxel centres, float64 ``[n, 3]`` (m; robot frame = world frame, floor plane at z = −L/2)."""
        return self.voxel_state()[VR.span("POS")].T.astype(np.float64)

    def orientations(self) -> np.ndarray:
        """Voxel orientation quaternions (w, x, y, z), float64 ``[n, 4]``."""
        return self.voxel_state()[VR.span("ORI")].T.astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Linear velocities, float64 ``[n, 3]``."""
        mass = material_table(self.config)[MT.MASS][self.layout.material]
        return self.voxel_state()[VR.span("MOM")].T.astype(np.float64) / mass[:, None]

    def link_strain(self) -> np.ndarray:
        """Axial strain of every link at its last update, float64 ``[m]``."""
        return self._table("lr")[LR.STRAIN].astype(np.float64)

    def static_friction(self) -> np.ndarray:
        """Floor static-friction state per voxel, bool ``[n]``."""
        return (self._table("vi")[VI.FLAGS] & STATIC) != 0

    # ------------------------------------------------------------------ the trace (summaries.py)
    def start_trace(self, every: int) -> None:
        """From now on, robot r's voxels are summarised (``summaries.SUMMARY``) into frame f of the trace when it
        has run f × ``every`` steps (since it was built; frame 0, its state now, is written here). Read with
        ``trace_frames``. Call before the first ``advance``."""
        self._check_owner()
        if not isinstance(every, int) or every < 1:
            raise ValueError(f"every must be a positive int (steps), got {every!r}")
        if self.steps_done:
            raise RuntimeError("start_trace must come before the first advance (frames count steps from 0): trace a "
                               "fresh engine (sim.engine(layout)); Simulator.finish(engine, trace_every=...) needs "
                               "one not yet advanced")
        R = self.counts["robots"]
        frames = 1 + _ceil_div(int(self.max_steps.max()), every) if R else 1  # no robot runs past its cap
        self._trace = self._arrays.grid("trace", (frames, SUMMARY.width, max(R, 1)))
        self.trace_steps = every
        self._summarise(0)

    def _summarise(self, frame: int) -> None:
        d = self._dev
        make_summaries(self.precision, self.order).summarise(d["vr"], d["vi"], d["rt"], d["ri"], d["mt"],
                                                             self.counts["robots"], self._trace, frame)

    def trace_frames(self) -> np.ndarray:
        """float64 ``[F, SUMMARY.width, R]``, once every robot has stopped: frame f summarises every robot after
        f × ``every`` steps, or as it stopped if it stopped before. F = 1 + ⌈the most steps any robot took / every⌉,
        where a diverged robot's last, failed step counts (the batch ran it: its frame says diverged)."""
        self._check_owner()
        if not self.trace_steps:
            raise RuntimeError("no trace: call start_trace(every) before advancing")
        R, k = self.counts["robots"], self.trace_steps
        if R == 0:
            return np.zeros((1, SUMMARY.width, 0))
        ri = self._table("ri")  # one copy for both: status and steps
        status, steps = ri[RI.STATUS], ri[RI.STEP].astype(np.int64)
        if (status == RUNNING).any():
            raise RuntimeError("trace_frames: robots are still running; advance until every robot has stopped "
                               "(Simulator.finish does), then read the trace")
        frames = 1 + _ceil_div(int((steps + (status == DIVERGED)).max()), k)
        # The last frame, taken now, is every robot as it stopped: a robot whose last step landed on it wrote the
        # same state there, and no robot that diverged did (its failed step does not count in its steps). A robot's
        # frames after its last trace step hold nothing it wrote: they repeat that state (status included).
        self._summarise(frames - 1)
        out = runtime.to_numpy(self._trace)[:frames, :, :R]
        stopped = np.arange(frames)[:, None] > (steps // k)[None, :]
        return np.where(stopped[:, None, :], out[-1:], out)

    def robot_status(self) -> np.ndarray:
        """int32 ``[R]``: RUNNING, DONE, DIVERGED or STALLED (stopped at its step cap)."""
        return self._table("ri")[RI.STATUS]

    def robot_steps(self) -> np.ndarray:
        """Steps each robot has run, int64 ``[R]``."""
        return self._table("ri")[RI.STEP].astype(np.int64)

    def robot_time(self) -> np.ndarray:
        """Each robot's clock, float64 ``[R]`` (s)."""
        return self._table("rt")[RT.T]

    def robot_dt(self) -> np.ndarray:
        """Each robot's current step, float64 ``[R]`` (s)."""
        return self._table("rt")[RT.DT]
