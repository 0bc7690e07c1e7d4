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
from typing import Any, NamedTuple

import numpy as np

from freeform.sim import native, runtime
from freeform.sim.access import make_transfers
from freeform.sim.config import SimConfig, material_table
from freeform.sim.initial import initial_state, recommended_dt
from freeform.sim.layout import Layout
from freeform.sim.packing import Packing, buffer_dtype
from freeform.sim.schedules import (
    COMMAND_ARGS,
    CONTROL_ARGS,
    FLAT_ARGS,
    ORDER_OF,
    SCHEDULES,
    UNROLL,
    block_dim_for,
    make_kernels,
    resolve_schedule,
)
from freeform.sim.state import (  # noqa: F401  (re-exported for tools and tests)
    BUFFERS,
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
    NO_LIMIT,
    RI,
    ROBOT_SENSE,
    RT,
    RUNNING,
    SENSE,
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

__all__ = ["SCHEDULES", "DeviceArrays", "Engine", "Readout", "recommended_dt"]

# A batch that outgrows the arrays gets this much room beyond its own size, so a run whose bodies grow slowly
# reallocates a logarithmic number of times, not every epoch.
CAPACITY_HEADROOM = 1.25
# a control step's compute graph (flat schedule) has a multiple of this many launches: few graphs per run
GRAPH_BUCKET = 8
INT32_MAX = np.iinfo(np.int32).max


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


class Readout(NamedTuple):
    """What a controller senses, as one copy back from the device (``Engine.sense``, ``Engine.control_step``)."""

    voxels: np.ndarray
    """float64 ``[n, SENSE.width]``: each voxel's position relative to its robot's centre of mass (m), velocity
    (m/s), mean |strain| of its links, ground contact (0/1), in the layout's voxel order."""
    com: np.ndarray
    """float64 ``[R, 3]``: every robot's centre of mass (m)."""
    time: np.ndarray
    """float64 ``[R]``: every robot's clock (s)."""
    status: np.ndarray
    """int32 ``[R]``: RUNNING, DONE, DIVERGED or STALLED."""


class DeviceArrays:
    """The kernels' buffers (``state.BUFFERS``), kept across Engines: each sized for the largest batch seen (item
    capacities grow with ``CAPACITY_HEADROOM`` and never shrink); items past a batch's own are stale and never read
    (the kernels' loops are bounded by the header's counts). Plus staging arrays (powers of two) through which the
    host reads and writes one region at a time.

    One Engine uses them at a time: building an Engine claims them, and an older Engine on the same arrays refuses
    to run or read (its state has been overwritten). ``allocations`` counts the device arrays made.
    """

    def __init__(self) -> None:
        self._arrays: dict[tuple[str, str], tuple[object, int]] = {}  # (name, dtype) -> (ndarray, length)
        self._capacity: dict[str, int] = {}
        self.allocations = 0
        self.owner: object | None = None

    def capacity(self, items: dict[str, int]) -> dict[str, int]:
        """Room in items for each kind in ``items`` (voxels, links, ...): what it was, or more where ``items``
        needs more."""
        for kind, n in items.items():
            if kind not in self._capacity or n > self._capacity[kind]:
                self._capacity[kind] = max(1, math.ceil(CAPACITY_HEADROOM * n))
        return {kind: self._capacity[kind] for kind in items}

    def buffer(self, name: str, dtype: np.dtype, length: int, keep: bool = False, host: bool = False):
        """The 1-D ndarray ``name`` of ``dtype`` with at least ``length`` elements, made or grown as needed (keep:
        a grown one starts with the old one's contents): (ndarray, its length). ``host``: a numpy array instead,
        which the CPU's kernels take in place (the native step's buffers: no copy around each advance)."""
        key = (name, np.dtype(dtype).name) + (("host",) if host else ())
        arr, have = self._arrays.get(key, (None, 0))
        if arr is None or length > have:
            old = runtime.to_numpy(arr) if (keep and arr is not None) else None
            have = max(length, math.ceil(CAPACITY_HEADROOM * have), 1)
            arr = np.zeros(have, np.dtype(dtype)) if host else runtime.ndarray(np.dtype(dtype), (have,))
            if old is not None:
                runtime.upload(arr, np.concatenate([old, np.zeros(have - old.size, dtype=old.dtype)]))
            self.allocations += 1
            self._arrays[key] = (arr, have)
        return arr, have

    def staging(self, dtype: np.dtype, n: int):
        """A staging ndarray of ``dtype`` with room for ``n`` elements (a power of two: few sizes over a run)."""
        return self.buffer("staging", dtype, 1 << max(6, (n - 1).bit_length()))

    def arrays(self) -> dict[tuple[str, str], object]:
        """The ndarrays held now, by (name, dtype) (tests check reuse through object identity)."""
        return {k: a for k, (a, _) in self._arrays.items()}


class Engine:
    """A batch of robots in Taichi ndarrays. ``advance(n)`` runs n steps of every still-running robot.

    schedule: "robots" (one worker per CPU thread taking whole robots from a queue, many steps per launch;
    the CPU default; arrays in "aos" order), "flat" (one thread per link/voxel/robot; the CUDA default; "soa") or
    "native" (the robots schedule's steps compiled by the host's C++ compiler, 8 or 16 items per vector instruction:
    ``native.py``; the f32 production path, Voxelyze semantics, a fixed dt, the flat floor; refused otherwise).
    "auto": ``schedules.resolve_schedule`` decides (on the CPU "native" where it runs the batch and is measured the
    faster, else "robots").
    Both compute the same physics (bit for bit in f64 up to fast-math reassociation, see docs/physics.md).
    arrays: the ``DeviceArrays`` to use (a Simulator passes its own, reused across batches); None = fresh ones.
    block_dim: the robots schedule's lanes per robot (``schedules.make_kernels``); None = 1 on the CPU, on CUDA
    ``schedules.block_dim_for`` the batch's largest robot. On the CPU a B > 1 runs the GPU's partition of each
    robot's work lane by lane (the same bits: a test of the GPU's indexing without a GPU).
    """

    def __init__(self, layout: Layout, config: SimConfig, arch: str = "auto", schedule: str = "auto",
                 arrays: DeviceArrays | None = None, block_dim: int | None = None):
        config.validate()
        self.arch = runtime.ensure(arch, config.backend)
        max_links = int(np.diff(layout.link_start).max()) if layout.num_robots else 0
        initial = initial_state(layout, config)
        self.schedule = resolve_schedule(schedule, self.arch, max_links, config.precision, initial.switches)
        self.layout, self.config = layout, config
        # one thread per robot walks its own voxels and links: keep each item's columns together ("aos", one
        # voxel = a few cache lines); one thread per item (GPU): neighbouring threads read neighbouring addresses
        # (on CUDA both schedules read "soa": a robot's block of threads reads neighbouring links and voxels)
        self.order = "soa" if self.arch == "cuda" else ORDER_OF[self.schedule]
        self.precision = config.precision
        self.np_real = np.float64 if config.precision == "f64" else np.float32
        self.rl4design = initial.switches.rl4design
        self.counts, self.dt0, self.max_steps = initial.counts, initial.dt0, initial.max_steps
        self.terrain, self.offset, self.switches = initial.terrain, initial.offset, initial.switches
        simt = self.arch == "cuda" and self.schedule == "robots"
        if block_dim is None:
            block_dim = block_dim_for(max_links, layout.num_robots) if simt else 1
        self.block_dim = block_dim if self.schedule == "robots" else 1
        self.kernels = make_kernels(config.precision, self.order, self.switches, self.block_dim, simt)
        self._transfers = make_transfers()
        R = layout.num_robots
        self._arrays = arrays if arrays is not None else DeviceArrays()
        self._arrays.owner = self
        grid = initial.height_grid
        self.packing = Packing(self._arrays.capacity({**self.counts, "cells": grid.size}), self.order)
        host = {**initial.tables, "gp": initial.globals[:, None], "hf": grid[None, :],
                "hdr": self.packing.header(self.counts)}
        self._buffers: dict[str, object] = {}
        for buffer, names in BUFFERS.items():
            dtype = buffer_dtype(buffer, self.precision)
            arr, length = self._arrays.buffer(buffer, dtype, self.packing.lengths[buffer], host=self._host_memory)
            runtime.upload(arr, self.packing.image(buffer, {n: host[n] for n in names if n in host}, dtype, length))
            self._buffers[buffer] = arr
        # robots schedule: one worker per CPU thread
        self._workers = max(1, min(R, runtime.num_threads()))
        self.steps_done = 0
        self.trace_steps = 0  # the trace (start_trace): off until asked for
        self._limit: np.ndarray | None = None  # each robot's clock limit while advance_time steps it
        # every robot's (clock, dt, status) as the last readout gave them; None once anything else steps or writes
        self._clock: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._commands, self._ramp = np.zeros(layout.num_voxels), 0.0  # the host's copies of VR.CMD and RT.RAMP

    # ------------------------------------------------------------------ host <-> device, one region at a time
    @property
    def _host_memory(self) -> bool:
        """Whether the state buffers are host (numpy) arrays: the native schedule's, where the C++ step and the
        CPU's kernels meet without copies."""
        return self.schedule == "native"

    @property
    def current(self) -> bool:
        """Whether this engine still owns its device arrays (a later Engine of the same Simulator takes them)."""
        return self._arrays.owner is self

    def _check_owner(self) -> None:
        if self._arrays.owner is not self:
            raise RuntimeError(
                "this Engine's device arrays were reused by a later Engine (a Simulator reuses one set of arrays "
                "across batches): read an Engine's results before building the next one from the same Simulator, "
                "or give each live Engine its own Simulator (or Engine(..., arrays=None))")

    def _upload(self, name: str, a: np.ndarray) -> None:
        """Write host ``a`` (``[columns, items]``, items ≤ the region's capacity) into region ``name``."""
        self._check_owner()
        if name in ("rt", "ri"):
            self._clock = None
        region = self.packing.regions[name]
        dtype = buffer_dtype(region.buffer, self.precision)
        stage = self._stage(region.flat(np.asarray(a, dtype=dtype)))
        self._transfers.write(self._buffers[region.buffer], region.at, 1, region.size, stage)

    def _stage(self, values: np.ndarray):
        """A staging ndarray holding ``values`` (1-D) at its start, for a copy kernel to write into a buffer."""
        stage, length = self._arrays.staging(values.dtype, values.size)
        padded = np.zeros(length, dtype=values.dtype)
        padded[: values.size] = values
        runtime.upload(stage, padded)
        return stage

    def _download(self, name: str) -> np.ndarray:
        """Host copy ``[columns, capacity]`` of region ``name`` (items past the batch's own are stale)."""
        self._check_owner()
        region = self.packing.regions[name]
        stage, _ = self._arrays.staging(buffer_dtype(region.buffer, self.precision), region.size)
        self._transfers.read(self._buffers[region.buffer], region.at, 1, region.size, stage)
        return region.unflat(runtime.to_numpy(stage), region.stride)

    def _column_place(self, name: str, column: int) -> tuple[object, int, int]:
        """(buffer, first element, step between items) of ``column`` of table ``name``."""
        region = self.packing.regions[name]
        if region.aos:
            return self._buffers[region.buffer], region.at + column, region.width
        return self._buffers[region.buffer], region.at + column * region.stride, 1

    def _write_column(self, name: str, column: int, values: np.ndarray) -> None:
        """Write one column of table ``name`` for this batch's items (``values`` ``[items]``): one copy kernel,
        whatever the memory order — what a controller does every control period."""
        self._check_owner()
        if name in ("rt", "ri"):  # (the robots' clocks or statuses may change: read them again)
            self._clock = None
        dtype = buffer_dtype(self.packing.regions[name].buffer, self.precision)
        stage = self._stage(np.asarray(values, dtype=dtype))
        buf, at, step = self._column_place(name, column)
        self._transfers.write(buf, at, step, values.size, stage)

    def _table(self, name: str) -> np.ndarray:
        """Host copy ``[columns, items]`` of table ``name``, this batch's items only."""
        return self._download(name)[:, : self.counts[TABLES[name].items]]

    # ------------------------------------------------------------------ stepping
    def advance(self, n_steps: int) -> None:
        """Run ``n_steps`` steps of every robot still running (finished, diverged or stalled robots stay frozen)."""
        self._check_owner()
        if n_steps <= 0 or self.layout.num_robots == 0:
            return
        if self._limit is not None:  # after advance_time: no limit again
            self._write_column("rt", RT.UNTIL, np.full(self.layout.num_robots, NO_LIMIT))
            self._limit = None
        self._advance(n_steps)

    def _advance(self, n_steps: int) -> None:
        self._clock = None
        k, buffers = self.kernels, tuple(self._buffers[name] for name in BUFFERS)
        if self.schedule == "robots":
            k.run_robots(*buffers, n_steps, self._workers)
        elif self.schedule == "native":  # the C++ step on the buffers themselves, host memory (native.py)
            native.advance(*buffers, n_steps, self._workers, self.switches)
        else:
            left = n_steps
            launches = self.config.graph_launches
            if left >= launches * UNROLL and (graph := k.flat_graph(launches)) is not None:
                bound = dict(zip(FLAT_ARGS, (*buffers, UNROLL), strict=True))
                while left >= launches * UNROLL:
                    graph.run(bound)
                    left -= launches * UNROLL
            while left > 0:
                k.run_flat(*buffers, min(left, UNROLL))
                left -= UNROLL
        self.steps_done += n_steps

    def advance_time(self, seconds) -> int:
        """Advance each robot until its own clock passes its next limit, ``seconds`` (a float, or float ``[R]`` per
        robot) after its previous one (the first: its clock now): a control period in simulated time, whatever each
        robot's dt (rl4design's differs per robot and over time). Limits accumulate from the last limit, not from
        the clock, so control times do not drift by each period's overshoot (< one dt). Finished, diverged or
        stalled robots stay frozen. Returns the steps issued (robots already past their limit idle through
        them); ``advance(n)`` afterwards runs without a limit again."""
        self._check_owner()
        R = self.layout.num_robots
        period = np.broadcast_to(np.asarray(seconds, dtype=np.float64), (R,))
        if not (np.isfinite(period).all() and (period > 0).all()):
            raise ValueError(f"seconds must be finite and > 0 (one value, or one per robot: {R}), got {seconds!r}")
        if R == 0:
            return 0
        start = self.robot_time() if self._limit is None else self._limit
        self._limit = start + period  # the host's copy of RT.UNTIL, written once per call
        self._write_column("rt", RT.UNTIL, self._limit)
        return self._run_to_limit()

    def _run_to_limit(self) -> int:
        """Step until every running robot's clock has passed its limit; the steps issued."""
        steps = 0
        while True:
            n = self._steps_to_limit(*self._read_clock(), self._limit)
            if n == 0:
                return steps
            self._advance(n)
            steps += n

    def _read_clock(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every robot's clock, dt and status, read back from the device."""
        rt = self._table("rt")
        return rt[RT.T].copy(), rt[RT.DT].copy(), self.robot_status()

    @staticmethod
    def _steps_to_limit(t: np.ndarray, dt: np.ndarray, status: np.ndarray, limit: np.ndarray) -> int:
        """The steps the furthest-behind running robot needs at its current dt to pass its limit (+1: it must pass
        it; a dt that shrinks meanwhile, rl4design's, only means another round), 0 when none is behind."""
        behind = (status == RUNNING) & (t < limit)
        return int(np.ceil(((limit - t) / dt)[behind].max())) + 1 if behind.any() else 0

    def control_step(self, commands, period: float, ramp: float = 0.0) -> Readout:
        """One control period in one call to the device: ``set_commands(commands, ramp)``, ``advance_time(period)``
        (``period`` one number of seconds for every robot) and ``sense()``, the same bits (tested), as one kernel
        launch on the robots schedule and one compute graph on the flat one (three launches and the steps' where
        the backend has no graphs, ``graph_launches`` is 0 or the period needs more than ``graph_launches``
        launches), with one upload of the commands and one copy back of the readout. The host knows each robot's
        clock from the last readout, so it issues the period's steps without asking (after anything else stepped
        the robots it reads their clocks once). A robot whose dt shrank within the period (rl4design) and is still
        behind gets another round and a second readout, as in ``advance_time``. ``steps_done`` counts the steps
        issued, which on the flat schedule's graph include the idle ones that round the launches up."""
        self._check_owner()
        c = self._checked_commands(commands, ramp)
        if np.ndim(period) != 0 or not (np.isfinite(period) and period > 0):
            raise ValueError(f"period must be one number of seconds, finite and > 0 (per-robot periods: "
                             f"advance_time), got {period!r}")
        t, dt, status = self._read_clock() if self._clock is None else self._clock
        from_clock = self._limit is None
        limit = (t if from_clock else self._limit) + float(period)  # what the device computes: the same sum
        n = self._steps_to_limit(t, dt, status, limit)
        stage, length = self._arrays.buffer("commands", np.dtype(np.float64), max(1, c.size))
        runtime.upload(stage, np.concatenate([c, np.zeros(length - c.size)]))
        out, _ = self._arrays.staging(np.dtype(np.float64), self._readout_size())
        k = self.kernels
        args = dict(zip(BUFFERS, (self._buffers[name] for name in BUFFERS), strict=True))
        args.update(commands=stage, out=out, period=float(period), ramp=float(ramp), from_clock=int(from_clock))
        # flat: launches rounded up to a multiple of GRAPH_BUCKET (idle steps), so that a period whose step count
        # wavers by one, or rl4design's, reuses a few graphs
        launches = min(_ceil_div(_ceil_div(n, UNROLL), GRAPH_BUCKET) * GRAPH_BUCKET, self.config.graph_launches)
        if self.layout.num_robots == 0:
            pass
        elif self.schedule == "robots":
            k.control_robots(*(args[name] for name in CONTROL_ARGS[:-1]), n, self._workers)
            self.steps_done += n
        elif (self.schedule == "flat" and self.config.graph_launches and launches * UNROLL >= n
              and (graph := k.control_graph(launches)) is not None):
            graph.run({**args, "n_steps": UNROLL})  # (every launch UNROLL steps: the last ones idle)
            self.steps_done += launches * UNROLL
        else:  # (native; flat without a graph)
            k.command(*(args[name] for name in COMMAND_ARGS))
            self._advance(n)
            k.sense(*(args[name] for name in (*BUFFERS, "out")))
        self._limit, self._commands, self._ramp = limit, c.copy(), float(ramp)
        readout = self._read(out)
        if self._steps_to_limit(*self._clock, limit):
            self._run_to_limit()
            readout = self._read(self._sense_into())
        return readout

    def snapshot(self) -> dict[str, Any]:
        """The batch's whole state now: a host copy of the three buffers and the host's own bookkeeping, which
        :meth:`restore` writes back so that the batch goes on as it would have from here, bit for bit (a control
        env restores its bodies' settled state at every episode instead of settling them again)."""
        self._check_owner()
        return {"buffers": {name: runtime.to_numpy(self._buffers[name]).copy() for name in BUFFERS},
                "counts": dict(self.counts), "packing": self.packing, "steps_done": self.steps_done,
                "trace_steps": self.trace_steps,
                "limit": None if self._limit is None else self._limit.copy(), "commands": self._commands.copy(),
                "ramp": self._ramp}

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Return to a :meth:`snapshot` of this engine, or of an engine of the same layout on the same simulator:
        the batch goes on as it would have from the snapshot, bit for bit. The device buffers may have grown since
        (another batch needed more room): the snapshot's packing comes back with it, and the buffers' tails past it
        are never read."""
        self._check_owner()
        if snapshot.get("counts", self.counts) != self.counts:
            raise ValueError(f"the snapshot holds another batch ({snapshot['counts']}) than this engine "
                             f"({self.counts}): restore a snapshot of this engine")
        for name in BUFFERS:
            saved, have = snapshot["buffers"][name], tuple(self._buffers[name].shape)
            if saved.shape[0] > have[0] or saved.shape[1:] != have[1:]:
                raise ValueError(f"the snapshot's {name} buffer has {saved.shape[0]} elements, this engine's "
                                 f"{have[0]}: restore a snapshot of this engine, taken after start_trace if it traces")
        for name in BUFFERS:
            saved = snapshot["buffers"][name]
            if saved.shape[0] < self._buffers[name].shape[0]:  # (grown since: the snapshot's part, zeros after)
                grown = np.zeros(tuple(self._buffers[name].shape), saved.dtype)
                grown[: saved.shape[0]] = saved
                saved = grown
            runtime.upload(self._buffers[name], saved)
        self.packing, self.steps_done = snapshot["packing"], snapshot["steps_done"]
        self.trace_steps = snapshot["trace_steps"]
        self._limit = None if snapshot["limit"] is None else snapshot["limit"].copy()
        self._commands, self._ramp = snapshot["commands"].copy(), snapshot["ramp"]
        self._clock = None

    def sense(self) -> Readout:
        """What a controller senses, gathered on the device in one kernel (``sensing.py``) and copied back once."""
        self._check_owner()
        return self._read(self._sense_into())

    def _readout_size(self) -> int:
        return self.layout.num_voxels * SENSE.width + self.layout.num_robots * ROBOT_SENSE.width

    def _sense_into(self):
        """The sensing array (a staging ndarray), filled by the ``sense`` kernel."""
        out, _ = self._arrays.staging(np.dtype(np.float64), self._readout_size())
        if self.layout.num_robots:
            self.kernels.sense(*(self._buffers[name] for name in BUFFERS), out)
        return out

    def _read(self, out) -> Readout:
        """The sensing array copied back as a readout; the robots' clocks, dts and statuses in it are the host's
        view of them until anything else steps or writes the robots (``_clock``: the next control step's steps)."""
        n, R = self.layout.num_voxels, self.layout.num_robots
        values = runtime.to_numpy(out)[: self._readout_size()]
        robots = values[n * SENSE.width:].reshape(R, ROBOT_SENSE.width)
        readout = Readout(voxels=values[: n * SENSE.width].reshape(n, SENSE.width),
                          com=robots[:, ROBOT_SENSE.span("COM")], time=robots[:, ROBOT_SENSE.T].copy(),
                          status=robots[:, ROBOT_SENSE.STATUS].astype(np.int32))
        self._clock = (readout.time.copy(), robots[:, ROBOT_SENSE.DT].copy(), readout.status.copy())
        return readout

    def set_commands(self, commands, ramp: float = 0.0) -> None:
        """Each voxel's actuation command (float ``[n]``, the layout's voxel order; numpy or a CPU tensor): from the
        next step on, its temperature is T_base + A·c (``SimConfig.actuation="command"``; c in [−1, 1] spans the
        sine's range, a passive voxel's CTE of 0 ignores it), or T_base + A·clip(sine + c, −1, 1) (``"residual"``:
        c in [−2, 2] reaches any temperature of the range from any phase). Commands hold until set again; they
        start at 0. ``ramp`` (s, > 0): each voxel's command moves linearly from the one in effect to the new one,
        reaching it at the next :meth:`advance_time` limit, ``ramp`` seconds after the ramp's start (a control
        period: a first-order hold — Voxelyze sets the rest size at once, so a jump of the command is an impulse);
        0: at once."""
        c = self._checked_commands(commands, ramp)
        if ramp > 0:  # (the command in effect when the ramp starts: the last one, reached by now)
            self._write_column("vr", VR.CMD0, self._commands.astype(self.np_real))
        if ramp != self._ramp:
            self._write_column("rt", RT.RAMP, np.full(self.layout.num_robots, float(ramp)))
            self._ramp = float(ramp)
        self._write_column("vr", VR.CMD, c.astype(self.np_real))
        self._commands = c.copy()

    def _checked_commands(self, commands, ramp: float) -> np.ndarray:
        """``commands`` as float64 ``[n]``, or a clear error."""
        if not self.switches.command:
            raise RuntimeError("commands need an engine built with SimConfig(actuation='command' or 'residual'); "
                               "this one runs the open-loop sine (actuation='sine')")
        c = np.asarray(commands, dtype=np.float64)
        if c.shape != (self.layout.num_voxels,):
            raise ValueError(f"commands must have shape ({self.layout.num_voxels},) (one per voxel), got {c.shape}")
        if not np.isfinite(c).all():
            raise ValueError("commands must be finite (a NaN or inf command would diverge its robot)")
        if not (np.isfinite(ramp) and ramp >= 0):
            raise ValueError(f"ramp must be >= 0 seconds, got {ramp!r}")
        return c

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
        # the trace is the last region of "f64s": room for it moves nothing else, so the clocks stay where they are
        self.packing = self.packing.with_trace(frames, max(R, 1))
        dtype = buffer_dtype("f64s", self.precision)
        self._buffers["f64s"], _ = self._arrays.buffer("f64s", dtype, self.packing.lengths["f64s"], keep=True,
                                                       host=self._host_memory)
        self.trace_steps = every
        self._upload("hdr", self.packing.header(self.counts, every))
        self._summarise(0)

    def _summarise(self, frame: int) -> None:
        make_summaries(self.precision, self.order).summarise(*(self._buffers[name] for name in BUFFERS), frame)

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
        tr = self._download("tr")  # [frames × SUMMARY.width, robots]
        out = tr.reshape(self.packing.trace_frames, SUMMARY.width, -1)[:frames, :, :R]
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
