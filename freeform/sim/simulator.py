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
from freeform.sim.state import DIVERGED, MT, RUNNING, STALLED, VR


@dataclass
class Recording:
    """Voxel poses at intervals, for rendering. F frames; per simulated-or-not body b (empty bodies: n_b = 0).

    times: float64 ``[F]`` seconds (of robot 0's clock; all robots share it unless rl4design varies dt).
    lattice[b]: int ``[n_b, 3]`` voxel index in the cropped body. materials[b]: uint8 ``[n_b]``.
    positions[b]: float32 ``[F, n_b, 3]`` metres, world frame, floor plane at z = −voxel_size/2.
    orientations[b]: float32 ``[F, n_b, 4]`` quaternions (w, x, y, z).
    """

    times: np.ndarray
    voxel_size: float
    lattice: list[np.ndarray]
    materials: list[np.ndarray]
    positions: list[np.ndarray]
    orientations: list[np.ndarray]


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
    recording: ``Recording`` or None.
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


class Simulator:
    """Voxelyze-model simulator of a batch of voxel bodies.

    ``arch``: "auto" (CUDA if present, else CPU with a warning) | "cpu" | "cuda"; Taichi is initialised once
    per process, on the first Simulator run. ``schedule``: "auto" | "robots" | "flat" (see ``Engine``; "robots"
    is refused on CUDA). Every batch reuses the Simulator's device arrays (``arrays``), grown only when a batch
    outgrows them; so one Engine of a Simulator is live at a time.
    """

    def __init__(self, config: SimConfig | None = None, arch: str = "auto", schedule: str = "auto"):
        self.config = config if config is not None else SimConfig()
        self.config.validate()
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

    def simulate(self, grids: torch.Tensor | np.ndarray, record_every: int | None = None) -> SimResult:
        """Simulate every body of ``grids`` (uint8 ``[B, X, Y, Z]``) for burn_in + duration seconds.

        record_every: if set, voxel poses are recorded at t = 0 and every ``record_every`` steps.
        """
        if record_every is not None and (not isinstance(record_every, int) or record_every < 1):
            raise ValueError(f"record_every must be None or a positive int, got {record_every!r}")
        layout = self.layout(grids)
        return self.run(layout, record_every)

    def run(self, layout: Layout, record_every: int | None = None) -> SimResult:
        """Simulate a prepared ``Layout`` (the hooks on it — fixed voxels, velocities — are honoured)."""
        return self.finish(self.engine(layout), record_every)

    def finish(self, engine: Engine, record_every: int | None = None) -> SimResult:
        """Run ``engine`` (from ``self.engine``, possibly advanced or edited already) until every robot has
        stopped, and give its results."""
        layout = engine.layout
        frames: list[tuple[float, np.ndarray]] = []

        def snapshot() -> None:
            vs = engine.voxel_state()
            t = float(engine.robot_time()[0]) if layout.num_robots else 0.0
            frames.append((t, vs[VR.POS:VR.ORI + 4].T.astype(np.float32).copy()))

        chunk = record_every if record_every is not None else self.config.chunk_steps
        if record_every is not None:
            snapshot()
        while layout.num_robots and (engine.robot_status() == RUNNING).any():
            engine.advance(chunk)
            if record_every is not None:
                snapshot()
        return self._result(engine, frames if record_every is not None else None)

    # ------------------------------------------------------------------ results
    def _result(self, engine: Engine, frames: list | None) -> SimResult:
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
            recording = self._recording(layout, frames)
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
        )

    def _recording(self, layout: Layout, frames: list) -> Recording:
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
                         positions=positions, orientations=orientations)
