"""``Simulator.simulate(grids) -> SimResult``: the public face of the physics engine.

A batch of bodies (uint8 ``[B, X, Y, Z]``, 0 = empty) is cropped, placed on the floor, flattened into one voxel
array and one link array, and advanced together until every robot has passed ``burn_in + duration`` (or
diverged). Empty bodies are not simulated and score 0; a diverged robot is stopped, flagged, and scores 0
without stopping the others; no NaN leaves the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from freeform.sim import runtime
from freeform.sim.config import SimConfig, material_table
from freeform.sim.engine import DeviceArrays, Engine
from freeform.sim.layout import Layout, build_layout
from freeform.sim.schedules import SCHEDULES, resolve_schedule
from freeform.sim.state import DIVERGED, MT, RUNNING, STALLED, SUMMARY, VR
from freeform.sim.terrain import FLAT, HeightField


@dataclass
class Recording:
    """Voxel poses at intervals, for rendering. F frames; per simulated-or-not body b (empty bodies: n_b = 0).

    times: float64 ``[F]`` seconds (of robot 0's clock; all robots share it unless rl4design varies dt).
    lattice[b]: int ``[n_b, 3]`` voxel index in the cropped body. materials[b]: uint8 ``[n_b]``.
    positions[b]: float32 ``[F, n_b, 3]`` metres, world frame, floor plane at z = −voxel_size/2.
    orientations[b]: float32 ``[F, n_b, 4]`` quaternions (w, x, y, z).
    ground: the terrain's surface the bodies stood on (``HeightField``; None: the flat floor), for drawing.
    """

    times: np.ndarray
    voxel_size: float
    lattice: list[np.ndarray]
    materials: list[np.ndarray]
    positions: list[np.ndarray]
    orientations: list[np.ndarray]
    ground: HeightField | None = None


@dataclass
class Trace:
    """Each robot's trajectory, sampled every ``every`` steps from t = 0 (before the first step) to its end:
    torch float64 CPU tensors, B bodies (one row per body passed in) × F samples. Positions are metres in the
    terrain's frame (the flat floor's plane at z = −L/2). The evaluation window is ``time > burn_in``.

    time ``[B, F]``: each robot's clock at the sample. valid ``[B, F]`` bool: the robot was still simulated (not
        empty, not yet diverged or stalled; a robot that has finished repeats its last state, valid).
    com ``[B, F, 3]``: centre of mass. z_min / z_max ``[B, F]``: lowest / highest voxel centre.
    bbox_min / bbox_max ``[B, F, 3]``: the voxel centres' bounding box. contacts ``[B, F]``: voxels touching the
        ground (at the start of their last step). orientation ``[B, F, 4]``: mean voxel orientation (w, x, y, z;
        each voxel's quaternion taken with w ≥ 0, averaged, normalised). voxels ``[B]``: voxels in the body.
    voxel_size, burn_in, duration: the protocol's (m, s, s).
    """

    time: torch.Tensor
    valid: torch.Tensor
    com: torch.Tensor
    z_min: torch.Tensor
    z_max: torch.Tensor
    bbox_min: torch.Tensor
    bbox_max: torch.Tensor
    contacts: torch.Tensor
    orientation: torch.Tensor
    voxels: torch.Tensor
    voxel_size: float
    burn_in: float
    duration: float
    every: int

    @property
    def evaluation(self) -> torch.Tensor:
        """bool ``[B, F]``: samples inside the evaluation window (t > burn_in) of a valid robot."""
        return self.valid & (self.time > self.burn_in)

    @property
    def burn_in_end(self) -> torch.Tensor:
        """long ``[B]``: the index of each robot's last sample at or before the end of the burn-in (the settled
        state that evaluation-window rewards start from)."""
        return ((self.time <= self.burn_in) & self.valid).sum(dim=1).clamp_min(1) - 1

    def to(self, device: torch.device | str) -> Trace:
        """A copy with every tensor on ``device``."""
        kw = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return Trace(**kw)


@dataclass
class SimResult:
    """Per-body results, torch CPU tensors with leading dimension B (one row per body passed in).

    displacement: float32 — the configured reward (``max_voxel`` or ``com``) in voxel lengths; 0 when
        empty or diverged.
    max_voxel_displacement: float32 — max over voxels of the horizontal distance between each voxel's
        position at the evaluation start and end, in voxel lengths.
    com_displacement: float32 — horizontal distance between the COM samples (taken once per actuation
        period) last before the evaluation start and end, in voxel lengths.
    com_start / com_end: float64 ``[B, 3]`` — those COM samples (metres, robot frame).
    diverged: bool — a link strain above max_strain or a non-finite state. stalled: bool — stopped at the step cap
        (SimConfig.step_cap) before the evaluation ended; it scores 0 too. simulated: bool (False for empty bodies).
    dt: float64 — each robot's initial step (s). steps: int64 — steps run. time: float64 — simulated seconds.
    recording: ``Recording`` or None. trace: ``Trace`` or None (``simulate(..., trace_every=...)``).
    """

    displacement: torch.Tensor
    max_voxel_displacement: torch.Tensor
    com_displacement: torch.Tensor
    com_start: torch.Tensor
    com_end: torch.Tensor
    diverged: torch.Tensor
    stalled: torch.Tensor
    simulated: torch.Tensor
    dt: torch.Tensor
    steps: torch.Tensor
    time: torch.Tensor
    recording: Recording | None = None
    trace: Trace | None = None


class Simulator:
    """Voxelyze-model simulator of a batch of voxel bodies.

    ``arch``: "auto" (CUDA if present, else CPU with a warning) | "cpu" | "cuda"; Taichi is initialised once
    per process, on the first Simulator run. ``schedule``: "auto" | "robots" | "flat" | "native" (see ``Engine``;
    "native" is refused on CUDA); None: the config's (``SimConfig.schedule``, ``sim.schedule`` in a run). Every batch reuses the Simulator's device arrays (``arrays``), grown only when a batch
    outgrows them; so one Engine of a Simulator is live at a time.
    """

    def __init__(self, config: SimConfig | None = None, arch: str = "auto", schedule: str | None = None):
        self.config = config if config is not None else SimConfig()
        self.config.validate()
        schedule = self.config.schedule if schedule is None else schedule
        if arch not in runtime.ARCHS:
            raise ValueError(f"arch must be one of {runtime.ARCHS}, got {arch!r}")
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
        if arch != "auto":
            resolve_schedule(schedule, arch)  # refuse a schedule the arch cannot run before anything starts
        self.arch = arch
        self.schedule = schedule
        self.arrays = DeviceArrays()

    def layout(self, grids: torch.Tensor | np.ndarray) -> Layout:
        """Validate and flatten ``grids`` (uint8 ``[B, X, Y, Z]``)."""
        return build_layout(grids, len(self.config.materials))

    def engine(self, layout: Layout) -> Engine:
        """A low-level ``Engine`` for ``layout`` (tests use this for fixed voxels, initial velocities...), on this
        Simulator's reused device arrays: an Engine built earlier from this Simulator stops working."""
        return Engine(layout, self.config, arch=self.arch, schedule=self.schedule, arrays=self.arrays)

    def simulate(self, grids: torch.Tensor | np.ndarray, record_every: int | None = None,
                 trace_every: float | None = None) -> SimResult:
        """Simulate every body of ``grids`` (uint8 ``[B, X, Y, Z]``) for burn_in + duration seconds.

        record_every: if set, voxel poses are recorded at t = 0 and every ``record_every`` steps (``Recording``).
        trace_every: if set (seconds), each robot's trajectory summary is sampled at t = 0 and about every
            ``trace_every`` seconds (a whole number of steps of the batch's median initial dt; ``Trace``).
        """
        if record_every is not None and (not isinstance(record_every, int) or record_every < 1):
            raise ValueError(f"record_every must be None or a positive int, got {record_every!r}")
        if trace_every is not None and not trace_every > 0:
            raise ValueError(f"trace_every must be None or > 0 seconds, got {trace_every!r}")
        layout = self.layout(grids)
        return self.run(layout, record_every, trace_every)

    def run(self, layout: Layout, record_every: int | None = None, trace_every: float | None = None) -> SimResult:
        """Simulate a prepared ``Layout`` (the hooks on it — fixed voxels, velocities — are honoured)."""
        return self.finish(self.engine(layout), record_every, trace_every)

    def finish(self, engine: Engine, record_every: int | None = None,
               trace_every: float | None = None) -> SimResult:
        """Run ``engine`` (from ``self.engine``, possibly edited already; advanced already only without a trace)
        until every robot has stopped, and give its results."""
        layout = engine.layout
        frames: list[tuple[float, np.ndarray]] = []

        def snapshot() -> None:
            t = float(engine.robot_time()[0]) if layout.num_robots else 0.0
            frames.append((t, engine.voxel_state()[VR.POS:VR.ORI + 4].T.astype(np.float32).copy()))

        trace_steps = None
        if trace_every is not None and layout.num_robots:
            # the kernels write each robot's samples as it steps: the batch never stops for one
            trace_steps = max(1, int(round(trace_every / float(np.median(engine.dt0)))))
            engine.start_trace(trace_steps)
        chunk = record_every if record_every is not None else self.config.chunk_steps
        if record_every is not None:
            snapshot()
        while layout.num_robots and (engine.robot_status() == RUNNING).any():
            engine.advance(chunk)
            if record_every is not None:
                snapshot()
        trace = self._trace(engine, trace_steps) if trace_every is not None else None
        return self._result(engine, frames if record_every is not None else None, trace)

    # ------------------------------------------------------------------ traces
    def _trace(self, engine: Engine, every: int | None) -> Trace:
        """The engine's trace frames (``Engine.trace_frames``) finished per body (``[B, F, ...]``, float64)."""
        layout, cfg = engine.layout, self.config
        B = layout.num_bodies
        rob = torch.from_numpy(layout.robot_of_body)
        has = rob >= 0
        idx = rob.clamp_min(0)
        sample: dict[str, torch.Tensor] = {}
        F = 0
        if every is not None:  # (robots exist)
            s = torch.from_numpy(engine.trace_frames()).permute(2, 0, 1)  # [R, F, SUMMARY.width]
            F = s.shape[1]
            q = s[..., SUMMARY.span("Q")]
            status = s[..., SUMMARY.STATUS].long()
            sample = {"time": s[..., SUMMARY.T], "com": s[..., SUMMARY.span("MX")] / s[..., SUMMARY.M, None],
                      "lo": s[..., SUMMARY.span("LO")], "hi": s[..., SUMMARY.span("HI")],
                      "contacts": s[..., SUMMARY.CONTACTS],
                      "orientation": q / q.norm(dim=-1, keepdim=True).clamp_min(1e-300),
                      "ok": ((status != DIVERGED) & (status != STALLED)).double()}

        def stack(key: str, width: tuple[int, ...] = ()) -> torch.Tensor:
            out = torch.zeros((B, F, *width), dtype=torch.float64)
            if F:
                out = torch.where(has.view(B, 1, *([1] * len(width))), sample[key][idx], out)
            return out

        valid = stack("ok") > 0.5 if F else torch.zeros((B, 0), dtype=torch.bool)
        lo, hi = stack("lo", (3,)), stack("hi", (3,))
        clean = lambda x: torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)  # noqa: E731
        voxels = torch.zeros(B, dtype=torch.float64)
        if layout.num_robots:
            counts = torch.from_numpy(np.diff(layout.voxel_start).astype(np.float64))
            voxels = torch.where(has, counts[idx], voxels)
        return Trace(time=stack("time"), valid=valid, com=clean(stack("com", (3,))), z_min=clean(lo[..., 2]),
                     z_max=clean(hi[..., 2]), bbox_min=clean(lo), bbox_max=clean(hi), contacts=stack("contacts"),
                     orientation=clean(stack("orientation", (4,))), voxels=voxels, voxel_size=cfg.voxel_size,
                     burn_in=cfg.burn_in, duration=cfg.duration, every=int(every or 0))

    # ------------------------------------------------------------------ results
    def _result(self, engine: Engine, frames: list | None, trace: Trace | None = None) -> SimResult:
        layout, cfg = engine.layout, self.config
        B, R = layout.num_bodies, layout.num_robots
        L = cfg.voxel_size
        vs = engine.voxel_state().astype(np.float64)
        vr_ = torch.from_numpy(layout.voxel_robot.astype(np.int64))
        status = engine.robot_status()
        diverged_r = torch.from_numpy(status == DIVERGED)
        stalled_r = torch.from_numpy(status == STALLED)

        def cols(c: int) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(vs[c:c + 3].T))

        # max over voxels of the horizontal displacement across the evaluation window
        dxy = (cols(VR.PEND) - cols(VR.PSTART))[:, :2].norm(dim=1) / L
        dxy = torch.nan_to_num(dxy, nan=0.0, posinf=0.0, neginf=0.0)
        max_vox = torch.zeros(R, dtype=torch.float64).scatter_reduce(0, vr_, dxy, reduce="amax", include_self=True)
        # mass-weighted COM of the period samples last taken before the start and the end
        mass = torch.from_numpy(material_table(cfg)[MT.MASS][layout.material])
        msum = torch.zeros(R, dtype=torch.float64).index_add_(0, vr_, mass)

        def com(c: int) -> torch.Tensor:
            acc = torch.zeros(R, 3, dtype=torch.float64).index_add_(0, vr_, cols(c) * mass[:, None])
            return acc / msum.clamp_min(torch.finfo(torch.float64).tiny)[:, None]

        com_s, com_e = com(VR.PCS), com(VR.PCE)
        com_d = (com_e - com_s)[:, :2].norm(dim=1) / L
        bad = diverged_r | stalled_r | ~torch.isfinite(com_d) | ~torch.isfinite(max_vox)
        max_vox = torch.where(bad, 0.0, max_vox)
        com_d = torch.where(bad, 0.0, com_d)
        com_s = torch.nan_to_num(com_s, nan=0.0, posinf=0.0, neginf=0.0)
        com_e = torch.nan_to_num(com_e, nan=0.0, posinf=0.0, neginf=0.0)
        disp = max_vox if cfg.reward == "max_voxel" else com_d

        rob = torch.from_numpy(layout.robot_of_body)
        has = rob >= 0
        idx = rob.clamp_min(0)

        def per_body(x: torch.Tensor, fill: float | bool = 0) -> torch.Tensor:
            if R == 0:
                return torch.full((B, *x.shape[1:]), fill, dtype=x.dtype)
            out = x[idx].clone()
            out[~has] = fill
            return out

        recording = None
        if frames is not None:
            recording = self._recording(layout, frames, engine.terrain)
        return SimResult(
            displacement=per_body(disp).float(),
            max_voxel_displacement=per_body(max_vox).float(),
            com_displacement=per_body(com_d).float(),
            com_start=per_body(com_s),
            com_end=per_body(com_e),
            diverged=per_body(bad & ~stalled_r, False) if R else torch.zeros(B, dtype=torch.bool),
            stalled=per_body(stalled_r, False) if R else torch.zeros(B, dtype=torch.bool),
            simulated=has.clone(),
            dt=per_body(torch.from_numpy(engine.dt0.astype(np.float64))),
            steps=per_body(torch.from_numpy(engine.robot_steps())),
            time=per_body(torch.from_numpy(engine.robot_time().astype(np.float64))),
            recording=recording,
            trace=trace,
        )

    def _recording(self, layout: Layout, frames: list, ground: HeightField) -> Recording:
        times = np.array([t for t, _ in frames])
        stack = np.stack([f for _, f in frames]) if frames else np.zeros((0, layout.num_voxels, 7), np.float32)
        stack = np.nan_to_num(stack, nan=0.0, posinf=0.0, neginf=0.0)
        lattice, materials, positions, orientations = [], [], [], []
        for b in range(layout.num_bodies):
            r = int(layout.robot_of_body[b])
            if r < 0:
                lo = hi = 0
            else:
                lo, hi = int(layout.voxel_start[r]), int(layout.voxel_start[r + 1])
            lattice.append(layout.lattice[lo:hi].astype(np.int64))
            materials.append(layout.material[lo:hi].astype(np.uint8))
            positions.append(np.ascontiguousarray(stack[:, lo:hi, 0:3]))
            # the frame holds POS, MOM, ORI columns in that order: ORI sits at offset 6
            orientations.append(np.ascontiguousarray(stack[:, lo:hi, VR.ORI - VR.POS:VR.ORI - VR.POS + 4]))
        return Recording(times=times, voxel_size=self.config.voxel_size, lattice=lattice, materials=materials,
                         positions=positions, orientations=orientations,
                         ground=None if ground.mode == FLAT else ground)
