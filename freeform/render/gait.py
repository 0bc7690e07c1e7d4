"""Gaits: a body simulated from rest, recorded, and drawn frame by frame.

A frame draws each voxel as a cube of the nominal voxel size at its recorded pose, a checkered floor fixed to the
world (so motion shows while the camera follows the robot), and the path of the centre of mass on the floor.
Building a :class:`~freeform.sim.Simulator` compiles Taichi kernels, so the short simulators behind gait videos are
kept in a :class:`SimulatorCache` rather than rebuilt every time training logs a video.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from freeform.render.raster import Camera, Canvas, RenderConfig, shade
from freeform.voxels import FACE_CORNERS, FACE_NORMALS, as_grid, check_recording, material_rgb

if TYPE_CHECKING:  # the type hints only: drawing a recording never needs Taichi
    from freeform.sim import Recording, Simulator


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` of quaternions ``[..., 4]`` (w, x, y, z; Hamilton, v' = q v q*)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def _covered_faces(lattice: np.ndarray) -> np.ndarray:
    """bool ``[n, 6]``: face d of voxel i touches another voxel of the body (a bonded, hidden face)."""
    if len(lattice) == 0:
        return np.zeros((0, 6), dtype=bool)
    lo = lattice.min(axis=0)
    idx = lattice - lo + 1  # one cell of padding on every side, so neighbours never index out of range
    occ = np.zeros(tuple(idx.max(axis=0) + 2), dtype=bool)
    occ[tuple(idx.T)] = True
    return np.stack([occ[tuple((idx + n).T)] for n in FACE_NORMALS], axis=1)


def com_trajectory(recording: Recording, robot: int = 0) -> np.ndarray:
    """Centre of mass of ``robot`` in every frame: float64 ``[F, 3]`` metres (voxel mean: the paper's materials
    share one density, so every voxel has the same mass)."""
    check_recording(recording, robot)
    return recording.positions[robot].astype(np.float64).mean(axis=1)


def render_recording(
    recording: Recording,
    robot: int = 0,
    config: RenderConfig | None = None,
    frames: Sequence[int] | np.ndarray | None = None,
    caption: bool = True,
) -> np.ndarray:
    """Frames of a recorded simulation (``Simulator.simulate(..., record_every=k).recording``).

    Draws robot ``robot``'s voxels as cubes of the nominal voxel size at their recorded poses, a checkered floor
    at z = −L/2 (tiles fixed to the world, so motion shows even when the camera follows), and the path of the
    centre of mass on the floor up to each frame. ``frames``: which frame indices (default: all).
    Returns RGB uint8 ``[F', size, size, 3]``.
    """
    cfg = config if config is not None else RenderConfig()
    cfg.validate()
    check_recording(recording, robot)
    L = float(recording.voxel_size)
    pos = recording.positions[robot].astype(np.float64)  # [F, n, 3]
    ori = recording.orientations[robot].astype(np.float64)  # [F, n, 4]
    n_frames = len(recording.times)
    chosen = np.arange(n_frames) if frames is None else np.asarray(frames, dtype=np.int64)
    if chosen.size and (chosen.min() < -n_frames or chosen.max() >= n_frames):
        raise ValueError(f"frames must index 0..{n_frames - 1}, got {chosen.tolist()}")
    covered = _covered_faces(np.asarray(recording.lattice[robot]))  # [n, 6]
    base = material_rgb(np.asarray(recording.materials[robot]), cfg.material_colors)  # [n, 3]
    camera = Camera.from_config(cfg)
    com = pos.mean(axis=1)  # [F, 3]
    floor_z = -L / 2.0
    start = com[0]

    # One framing for the whole video (so the scale does not breathe): the robot's largest half-extent plus a view
    # radius, around its centre of mass (follow) or around the whole trajectory (fixed).
    half = float(np.max(np.abs(pos - com[:, None, :]))) + L
    radius = half + cfg.view_radius * L
    top = float(pos[..., 2].max()) + L
    if not cfg.follow:
        lo_xy, hi_xy = com[:, :2].min(axis=0), com[:, :2].max(axis=0)
        radius = max(radius, float(np.max(hi_xy - lo_xy)) / 2.0 + half + 2 * L)
        fixed_centre = np.array([(lo_xy[0] + hi_xy[0]) / 2, (lo_xy[1] + hi_xy[1]) / 2])

    out = np.empty((len(chosen), cfg.size, cfg.size, 3), dtype=np.uint8)
    light_normals = FACE_NORMALS.astype(np.float64)
    for i, f in enumerate(chosen.tolist()):  # frames are independent images; the work inside is vectorised
        centre_xy = com[f, :2] if cfg.follow else fixed_centre
        box = np.array([[centre_xy[0] + sx * radius, centre_xy[1] + sy * radius, z]
                        for sx in (-1, 1) for sy in (-1, 1) for z in (floor_z, top)])
        canvas = Canvas(cfg, camera, box)

        # Floor: world-aligned checker tiles covering the view (drawn first: nothing is ever below it).
        tile = cfg.floor_tile * L
        seen = canvas.floor_bounds(floor_z)
        lo_f, hi_f = seen if seen is not None else (centre_xy - 1.5 * radius, centre_xy + 1.5 * radius)
        lo_f, hi_f = np.maximum(lo_f, centre_xy - 10 * radius), np.minimum(hi_f, centre_xy + 10 * radius)  # grazing
        i0, i1 = math.floor(lo_f[0] / tile), math.ceil(hi_f[0] / tile)
        j0, j1 = math.floor(lo_f[1] / tile), math.ceil(hi_f[1] / tile)
        ii, jj = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1), indexing="ij")
        ii, jj = ii.ravel(), jj.ravel()
        sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
        xy = (np.stack([ii, jj], axis=1)[:, None, :] + sq[None]) * tile  # [T, 4, 2]
        floor = np.concatenate([xy, np.full(xy.shape[:2] + (1,), floor_z)], axis=2)
        floor_rgb = np.asarray(cfg.floor_colors, dtype=np.float64)[(ii + jj) % 2]
        canvas.quads(floor, floor_rgb, np.ones(len(floor)), outline=False)

        # Trace of the centre of mass, on the floor.
        path = np.concatenate([com[: f + 1, :2], np.full((f + 1, 1), floor_z)], axis=1)
        canvas.polyline(path, cfg.trace_color, cfg.trace_width)
        canvas.dot(np.array([start[0], start[1], floor_z]), cfg.trace_color, cfg.trace_width * 1.5)

        # Robot: each voxel a cube at its pose; faces bonded to a neighbour or turned away are skipped.
        rot = quat_to_matrix(ori[f])  # [n, 3, 3]
        normals = np.einsum("nij,dj->ndi", rot, light_normals)  # [n, 6, 3]
        visible = ~covered & (normals @ camera.towards > 1e-9)
        vi, di = np.nonzero(visible)
        local = FACE_CORNERS[di] * (L / 2.0)  # [q, 4, 3]
        corners = pos[f][vi][:, None, :] + np.einsum("qij,qkj->qki", rot[vi], local)
        rgb = shade(normals[vi, di], base[vi], cfg)
        order = np.argsort(corners.mean(axis=1) @ camera.towards, kind="stable")
        canvas.quads(corners[order], rgb[order], np.ones(len(order)))

        lines: list[str] = []
        if caption:
            disp = float(np.linalg.norm(com[f, :2] - start[:2])) / L
            lines = [f"t = {recording.times[f]:.2f} s", f"COM moved {disp:.2f} voxels"]
        out[i] = canvas.finish(lines)
    return out


@dataclass
class VideoConfig:
    """The gait video logged during training (and the default of ``freeform-render --video``)."""

    seconds: float = 1.5
    """Simulated seconds shown (from t = 0: settling, then the gait; 6 actuation periods at 4 Hz). Short because
    training simulates it every ``render_every`` epochs: 2 s cost 5.6 % of a locomotion CPU-demo epoch at
    ``render_every=10``, over the 5 % budget (``python -m benchmarks render``)."""
    fps: float = 20.0
    """Frames per simulated second, and the playback rate (real time)."""
    size: int = 192
    """Edge of the video frames in pixels."""


def _frame_every(simulator: Simulator, fps: float) -> int:
    """Steps between recorded frames for ``fps`` frames per simulated second."""
    cfg = simulator.config
    dt = cfg.dt if cfg.dt is not None else cfg.dt_frac * _REST_DT_ESTIMATE
    return max(1, int(round(1.0 / (fps * dt))))


# Voxelyze's recommended dt of the paper's material (spec section 10, ν = 0.35, at rest); only sets the frame
# spacing of a video when the simulator chooses dt itself, the recorded times stay exact.
_REST_DT_ESTIMATE = 1.240490e-4


def simulate_gait(simulator: Simulator, body: np.ndarray, fps: float = 20.0) -> Recording:
    """Simulate one ``body`` (uint8 ``[X, Y, Z]``) with ``simulator``, recording ``fps`` frames per second."""
    b = as_grid(body, "body", 3)
    result = simulator.simulate(b[None], record_every=_frame_every(simulator, fps))
    if result.recording is None:
        raise ValueError("the simulator returned no recording")
    return result.recording


class SimulatorCache:
    """Simulators of settings shortened to a gait video's length, one per (settings, arch), built on first use.

    Building a ``Simulator`` compiles its kernels; training asks for the same one every ``render_every`` epochs.
    """

    def __init__(self) -> None:
        self._simulators: dict[tuple[str, str], Simulator] = {}

    def get(self, sim_config: Any, seconds: float, arch: str = "auto") -> Simulator:
        """A ``Simulator`` of ``sim_config`` shortened to ``seconds`` from t = 0 (no burn-in)."""
        from freeform.sim import Simulator

        short = replace(sim_config, burn_in=0.0, duration=float(seconds))
        key = (repr(short), arch)  # a SimConfig is a mutable dataclass, unhashable: its repr stands in
        if key not in self._simulators:
            self._simulators[key] = Simulator(short, arch=arch)
        return self._simulators[key]

    def clear(self) -> None:
        """Drop every cached simulator (and with it its Taichi fields)."""
        self._simulators.clear()

    def __len__(self) -> int:
        return len(self._simulators)


GAIT_SIMULATORS = SimulatorCache()
"""The process-wide cache behind :func:`gait_simulator` (training's video hook and ``freeform-render``)."""


def gait_simulator(sim_config: Any, seconds: float, arch: str = "auto") -> Simulator:
    """A ``Simulator`` of ``sim_config`` shortened to ``seconds`` from t = 0 (no burn-in), cached per settings in
    :data:`GAIT_SIMULATORS`."""
    return GAIT_SIMULATORS.get(sim_config, seconds, arch)


__all__ = [
    "GAIT_SIMULATORS",
    "SimulatorCache",
    "VideoConfig",
    "com_trajectory",
    "gait_simulator",
    "quat_to_matrix",
    "render_recording",
    "simulate_gait",
]
