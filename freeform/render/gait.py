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

from freeform.render.raster import Camera, Canvas, RenderConfig, lambert, shade
from freeform.sim.terrain import COLUMNS, SMOOTH, Terrain
from freeform.surface import FACE_CORNERS, FACE_NORMALS, as_grid, check_recording, material_rgb

if TYPE_CHECKING:  # the type hints only: drawing a recording never needs Taichi
    from freeform.sim import Recording, Simulator
    from freeform.sim.terrain import HeightField


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


# Quads per tile edge on a bumpy smooth terrain: half a height-field cell each, at most this many (a 4 cm bump
# wavelength on 1 cm voxels and 2-voxel tiles gives 8).
_MAX_SUBDIVISION = 8


def _breaks(lo: float, hi: float, tile: float, sub: int, cells: np.ndarray | None) -> np.ndarray:
    """Sorted cut positions along one axis: tile edges (each split in ``sub``) plus ``cells`` (column edges)."""
    start, stop = math.floor(lo / tile), math.ceil(hi / tile)
    cuts = np.arange(start * sub, stop * sub + 1, dtype=np.float64) * (tile / sub)
    if cells is not None:
        cuts = np.sort(np.concatenate([cuts, cells[(cells > cuts[0]) & (cells < cuts[-1])]]))
        cuts = cuts[np.concatenate([[True], np.diff(cuts) > 1e-9 * tile])]  # a column edge on a tile edge: once
    return cuts


def _risers(top: np.ndarray, xs: np.ndarray, ys: np.ndarray, towards: np.ndarray, colour: np.ndarray
            ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The vertical faces between columns of tops ``top [nx-1, ny-1]`` (cut at ``xs``, ``ys``) where neighbouring
    tops differ, each on the shared edge facing the lower top, the faces turned away from the camera (``towards``)
    left out: per axis, (corners ``[Q, 4, 3]``, colours ``[Q, 3]`` — the quad's own ``colour [nx-1, ny-1, 3]`` —,
    normals ``[Q, 3]``)."""
    out = []
    for axis in (0, 1):
        a, b = (top[:-1], top[1:]) if axis == 0 else (top[:, :-1], top[:, 1:])
        facing = np.sign(a - b)  # +1: the face looks towards +axis (the lower top lies there)
        seen = facing * towards[axis] > 0  # faces turned away from the camera are hidden behind a tread
        i, j = np.nonzero(seen)
        if not len(i):
            continue
        lo_z, hi_z = np.minimum(a, b)[i, j], np.maximum(a, b)[i, j]
        if axis == 0:  # the face at x = xs[i + 1] spanning the quad's y range
            p, q0, q1 = xs[i + 1], ys[j], ys[j + 1]
            face = [np.stack([p, q0, lo_z], -1), np.stack([p, q1, lo_z], -1), np.stack([p, q1, hi_z], -1),
                    np.stack([p, q0, hi_z], -1)]
        else:
            p, q0, q1 = ys[j + 1], xs[i], xs[i + 1]
            face = [np.stack([q0, p, lo_z], -1), np.stack([q1, p, lo_z], -1), np.stack([q1, p, hi_z], -1),
                    np.stack([q0, p, hi_z], -1)]
        normal = np.zeros((len(i), 3))
        normal[:, axis] = facing[i, j]
        out.append((np.stack(face, axis=1), colour[i, j], normal))
    return out


def ground_quads(ground: HeightField, lo: np.ndarray, hi: np.ndarray, tile: float,
                 cfg: RenderConfig) -> tuple[np.ndarray, np.ndarray]:
    """The terrain over the (x, y) box ``lo``..``hi`` as quads ``[Q, 4, 3]`` and colours ``[Q, 3]``, in drawing
    order (far first).

    The checker of the flat floor (tiles of edge ``tile``, colour by the tile a quad lies in), bent over the
    surface: a smooth terrain as small quads with their corners on it (a plane needs no subdivision), a columnar
    one (stairs, ``smooth=False`` height maps) as flat tops cut at the column edges plus the vertical faces
    between columns of different height. Shaded by each quad's normal relative to the flat floor's, so flat
    ground keeps the floor's colours and relief shows.
    """
    towards = Camera.from_config(cfg).towards
    columns = ground.mode == COLUMNS
    bumpy = ground.mode == SMOOTH and float(np.ptp(ground.grid)) > 0
    sub = min(_MAX_SUBDIVISION, max(1, math.ceil(tile / (ground.cell / 2)))) if bumpy else 1
    col_x = ground.x0 + ground.cell * np.arange(1, ground.nx) if columns else None
    col_y = ground.y0 + ground.cell * np.arange(1, ground.ny) if columns else None
    xs, ys = _breaks(lo[0], hi[0], tile, sub, col_x), _breaks(lo[1], hi[1], tile, sub, col_y)
    X, Y = np.meshgrid(xs, ys, indexing="ij")  # cut points [nx, ny]
    cx, cy = (X[:-1, :-1] + X[1:, 1:]) / 2, (Y[:-1, :-1] + Y[1:, 1:]) / 2  # quad centres [nx-1, ny-1]
    if columns:  # flat tops: every corner at the column's height under the quad's centre
        top = ground.height(cx, cy)
        z = [top, top, top, top]
    else:
        Z = ground.height(X, Y)
        z = [Z[:-1, :-1], Z[1:, :-1], Z[1:, 1:], Z[:-1, 1:]]
    xy = [(X[:-1, :-1], Y[:-1, :-1]), (X[1:, :-1], Y[1:, :-1]), (X[1:, 1:], Y[1:, 1:]), (X[:-1, 1:], Y[:-1, 1:])]
    quads = np.stack([np.stack([x, y, zz], axis=-1) for (x, y), zz in zip(xy, z, strict=True)], axis=-2)
    checker = (np.floor(cx / tile) + np.floor(cy / tile)).astype(np.int64) % 2
    corners, colours = [quads.reshape(-1, 4, 3)], [np.asarray(cfg.floor_colors)[checker.ravel()]]
    # a quad's normal from its diagonals (exactly +z on level ground: flat floors and columns' tops)
    n = np.cross(corners[0][:, 2] - corners[0][:, 0], corners[0][:, 3] - corners[0][:, 1])
    normals = [n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)]
    if columns:  # risers: where neighbouring tops differ, a vertical face on their shared edge, facing the lower
        for part, rgb, normal in _risers(top, xs, ys, towards, np.asarray(cfg.floor_colors)[checker]):
            corners.append(part)
            colours.append(rgb)
            normals.append(normal)
    corners_all, rgb, normal_all = np.concatenate(corners), np.concatenate(colours), np.concatenate(normals)
    # relief: each quad's Lambert factor over level ground's, so level ground keeps the floor's colours exactly
    relief = (lambert(normal_all, cfg) / lambert(np.array([[0.0, 0.0, 1.0]]), cfg))[:, None]
    # drawing order: far quads first where they can hide one another; level ground keeps the checker's own order
    depth = corners_all.mean(axis=1) @ towards
    order = np.argsort(depth, kind="stable") if np.ptp(corners_all[..., 2]) > 0 else np.arange(len(depth))
    return corners_all[order], np.clip(rgb * relief, 0.0, 1.0)[order]


@dataclass
class _Scene:
    """What every frame of one robot's recording draws from: its poses ``pos [F, n, 3]``, ``ori [F, n, 4]``, centre
    of mass ``com [F, 3]`` and its path's height on the ground ``path_z [F]``, each voxel's covered faces ``[n, 6]``
    and colour ``[n, 3]``, the ground, the framing (``radius`` around the centre of mass, or around ``centre`` for a
    fixed camera; ``top``, the highest point), the voxel size ``L``, the camera and the config."""

    pos: np.ndarray
    ori: np.ndarray
    com: np.ndarray
    path_z: np.ndarray
    covered: np.ndarray
    base: np.ndarray
    ground: HeightField
    radius: float
    top: float
    centre: np.ndarray | None
    L: float
    camera: Camera
    cfg: RenderConfig


def render_recording(
    recording: Recording,
    robot: int = 0,
    config: RenderConfig | None = None,
    frames: Sequence[int] | np.ndarray | None = None,
    caption: bool = True,
) -> np.ndarray:
    """Frames of a recorded simulation (``Simulator.simulate(..., record_every=k).recording``).

    Draws robot ``robot``'s voxels as cubes of the nominal voxel size at their recorded poses, the checkered ground
    (the flat floor at z = −L/2, or the recording's terrain with its relief shaded; tiles fixed to the world, so
    motion shows even when the camera follows), and the path of the centre of mass on the ground up to each
    frame. ``frames``: which frame indices (default: all).
    Returns RGB uint8 ``[F', size, size, 3]``.
    """
    cfg = config if config is not None else RenderConfig()
    cfg.validate()
    check_recording(recording, robot)
    n_frames = len(recording.times)
    chosen = np.arange(n_frames) if frames is None else np.asarray(frames, dtype=np.int64)
    if chosen.size and (chosen.min() < -n_frames or chosen.max() >= n_frames):
        raise ValueError(f"frames must index 0..{n_frames - 1}, got {chosen.tolist()}")
    scene = _scene(recording, robot, cfg)
    out = np.empty((len(chosen), cfg.size, cfg.size, 3), dtype=np.uint8)
    for i, f in enumerate(chosen.tolist()):  # frames are independent images; the work inside is vectorised
        lines: list[str] = []
        if caption:
            disp = float(np.linalg.norm(scene.com[f, :2] - scene.com[0, :2])) / scene.L
            lines = [f"t = {recording.times[f]:.2f} s", f"COM moved {disp:.2f} voxels"]
        out[i] = _draw_frame(scene, f).finish(lines)
    return out


def _scene(recording: Recording, robot: int, cfg: RenderConfig) -> _Scene:
    """Robot ``robot``'s recording made ready to draw, with one framing for the whole video (so the scale does not
    breathe): the robot's largest half-extent plus a view radius, around its centre of mass (follow) or around
    the whole trajectory (fixed)."""
    L = float(recording.voxel_size)
    pos = recording.positions[robot].astype(np.float64)  # [F, n, 3]
    com = pos.mean(axis=1)  # [F, 3]
    ground = recording.ground if recording.ground is not None else Terrain.flat().field(L)
    half = float(np.max(np.abs(pos - com[:, None, :]))) + L
    radius = half + cfg.view_radius * L
    centre = None
    if not cfg.follow:
        lo_xy, hi_xy = com[:, :2].min(axis=0), com[:, :2].max(axis=0)
        radius = max(radius, float(np.max(hi_xy - lo_xy)) / 2.0 + half + 2 * L)
        centre = np.array([(lo_xy[0] + hi_xy[0]) / 2, (lo_xy[1] + hi_xy[1]) / 2])
    return _Scene(pos=pos, ori=recording.orientations[robot].astype(np.float64), com=com,
                  path_z=ground.height(com[:, 0], com[:, 1]),  # the path lies on the ground (drawn after it)
                  covered=_covered_faces(np.asarray(recording.lattice[robot])),
                  base=material_rgb(np.asarray(recording.materials[robot]), cfg.material_colors), ground=ground,
                  radius=radius, top=float(pos[..., 2].max()) + L, centre=centre, L=L,
                  camera=Camera.from_config(cfg), cfg=cfg)


def _draw_frame(scene: _Scene, f: int) -> Canvas:
    """Frame ``f`` of ``scene`` drawn on a canvas (to be finished with its caption): the ground, the path of the
    centre of mass on it, and the robot."""
    cfg, radius, ground, com = scene.cfg, scene.radius, scene.ground, scene.com
    centre_xy = com[f, :2] if scene.centre is None else scene.centre
    # the ground under the framed square sets its lowest and highest point
    gx, gy = np.meshgrid(*(np.linspace(c - radius, c + radius, 9) for c in centre_xy), indexing="ij")
    heights = ground.height(gx, gy)
    ground_lo, ground_hi = float(heights.min()), float(heights.max())
    box = np.array([[centre_xy[0] + sx * radius, centre_xy[1] + sy * radius, z]
                    for sx in (-1, 1) for sy in (-1, 1) for z in (ground_lo, max(scene.top, ground_hi))])
    canvas = Canvas(cfg, scene.camera, box)

    # Ground: world-aligned checker tiles covering the view (drawn first: nothing is ever below it).
    seen = [b for b in (canvas.floor_bounds(z) for z in (ground_lo, ground_hi)) if b is not None]
    if seen:
        lo_f, hi_f = np.min([b[0] for b in seen], axis=0), np.max([b[1] for b in seen], axis=0)
    else:
        lo_f, hi_f = centre_xy - 1.5 * radius, centre_xy + 1.5 * radius
    lo_f, hi_f = np.maximum(lo_f, centre_xy - 10 * radius), np.minimum(hi_f, centre_xy + 10 * radius)  # grazing
    corners_g, rgb_g = ground_quads(ground, lo_f, hi_f, cfg.floor_tile * scene.L, cfg)
    canvas.quads(corners_g, rgb_g, np.ones(len(corners_g)), outline=False)

    # Trace of the centre of mass, on the ground.
    path = np.concatenate([com[: f + 1, :2], scene.path_z[: f + 1, None]], axis=1)
    canvas.polyline(path, cfg.trace_color, cfg.trace_width)
    canvas.dot(np.array([com[0, 0], com[0, 1], scene.path_z[0]]), cfg.trace_color, cfg.trace_width * 1.5)

    # Robot: each voxel a cube at its pose; faces bonded to a neighbour or turned away are skipped.
    rot = quat_to_matrix(scene.ori[f])  # [n, 3, 3]
    normals = np.einsum("nij,dj->ndi", rot, FACE_NORMALS.astype(np.float64))  # [n, 6, 3]
    visible = ~scene.covered & (normals @ scene.camera.towards > 1e-9)
    vi, di = np.nonzero(visible)
    local = FACE_CORNERS[di] * (scene.L / 2.0)  # [q, 4, 3]
    corners = scene.pos[f][vi][:, None, :] + np.einsum("qij,qkj->qki", rot[vi], local)
    rgb = shade(normals[vi, di], scene.base[vi], cfg)
    order = np.argsort(corners.mean(axis=1) @ scene.camera.towards, kind="stable")
    canvas.quads(corners[order], rgb[order], np.ones(len(order)))
    return canvas


@dataclass
class VideoConfig:
    """The gait video logged during training (and the default of ``freeform-render --video``)."""

    seconds: float = 1.5
    """Simulated seconds shown (from t = 0: settling, then the gait; 6 actuation periods at 4 Hz). Short because
    training simulates it every ``render_every`` epochs, within the 5 % of an epoch renders may cost
    (``python -m benchmarks render``, docs/rendering.md)."""
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
    "ground_quads",
    "quat_to_matrix",
    "render_recording",
    "simulate_gait",
]
