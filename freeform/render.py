"""Seeing the robots: shaded images of voxel designs, videos of simulated gaits, and their TensorBoard summaries.

Everything here is a small orthographic rasteriser on top of Pillow (already installed as a dependency of
TensorBoard): the visible faces of the voxels are built as one numpy array of quads, sorted back to front
(painter's algorithm — exact enough for unit cubes on a grid, and for the slightly rotated cubes of a gait), shaded
with one directional light, and filled with Pillow's C polygon filler at twice the size, then box-filtered down
(anti-aliasing). A 20³ design renders in about 10 ms, so logging a few images every few epochs costs nothing
measurable (``benchmarks/bench_render.py``).

Colours are the paper's (its figures 1-2): passive tissue blue, muscle A green, muscle B red; the voxels of the
final grid that are *not* in the body (the largest connected component) are drawn translucent grey, as in the
paper's "body after a_100" panel.

Public API
- :class:`RenderConfig` — camera, light, colours, sizes (every number a field with its default).
- :func:`render_grid` / :func:`render_grids` — design grids ``[ρ, ρ, ρ]`` / ``[N, ρ, ρ, ρ]`` uint8 → RGB
  ``[H, W, 3]`` / ``[N, H, W, 3]`` uint8.
- :func:`render_recording` — a ``freeform.sim.Recording`` → frames ``[F, H, W, 3]`` uint8 (deformed voxels,
  checkered floor, trace of the centre of mass).
- :func:`contact_sheet` — many images → one sheet (``freeform-render --grid``).
- :func:`encode_gif`, :func:`write_video` (``.gif`` with Pillow, ``.mp4`` with the optional ``video`` extra),
  :func:`write_png`.
- :func:`add_gif` — an animated GIF into a TensorBoard event file (no moviepy needed).
- :func:`log_epoch_renders` — what the training loop calls every ``trainer.render_every`` epochs: the best, the
  median and a random body as images and, given a simulator, a GIF of the best robot's gait.
  :func:`log_bodies` is the same behind the trainer's ``(writer, final_grids, rewards, step, cfg)`` hook.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

if TYPE_CHECKING:  # imported for type hints only: rendering a grid never needs Taichi or TensorBoard
    from torch.utils.tensorboard import SummaryWriter

    from freeform.sim import Recording, Simulator

RGB = tuple[float, float, float]

# Material colours of the paper's figures (index i is material i + 1; 0 = empty has no colour).
PAPER_COLORS: tuple[RGB, ...] = (
    (0.13, 0.42, 0.93),  # 1 passive tissue: blue
    (0.33, 0.78, 0.16),  # 2 muscle A (phase 0): green
    (0.89, 0.16, 0.13),  # 3 muscle B (phase 0.5): red
    (0.95, 0.70, 0.10),  # further materials, should a task define them
    (0.60, 0.30, 0.80),
    (0.10, 0.75, 0.75),
)


@dataclass
class RenderConfig:
    """How an image is drawn. Angles in degrees; colours are RGB in [0, 1].

    The default camera is matplotlib's 3-D default (azimuth −60°, elevation 30°), the view of the paper's figures.
    """

    size: int = 256
    """Edge of the square image in pixels."""
    supersample: int = 2
    """Draw at this multiple of ``size`` and box-filter down (anti-aliasing); 1 = off."""
    azimuth: float = -60.0
    """Camera azimuth about +z, from +x towards +y."""
    elevation: float = 30.0
    """Camera elevation above the xy-plane."""
    light: tuple[float, float, float] = (0.3, -0.6, 1.0)
    """Direction towards the light (world frame; normalised when used)."""
    ambient: float = 0.45
    """Brightness of a face turned away from the light."""
    diffuse: float = 0.6
    """Extra brightness of a face facing the light (Lambert)."""
    material_colors: tuple[RGB, ...] = PAPER_COLORS
    """Colour of material i + 1 (cycled when a grid has more materials)."""
    removed_color: RGB = (0.55, 0.55, 0.55)
    """Colour of the final grid's voxels outside the body."""
    removed_alpha: float = 0.28
    """Opacity of those voxels."""
    edge_darkening: float = 0.6
    """Voxel outlines are the face colour times this (0 = black, 1 = no outlines)."""
    background: RGB = (1.0, 1.0, 1.0)
    pane_color: RGB = (0.93, 0.93, 0.94)
    """The design grid's three back walls (as matplotlib's axes panes in the paper's figure)."""
    show_panes: bool = True
    """Draw the back walls of the ρ³ design space behind a design."""
    frame: str = "grid"
    """Framing of a design: "grid" (the whole ρ³ design space, the same scale for every design) or "body"
    (zoomed to the drawn voxels)."""
    margin: float = 0.06
    """Empty border around the framed content, as a fraction of the image."""
    # --- gait videos -------------------------------------------------------------------------------------------
    floor_colors: tuple[RGB, RGB] = ((0.86, 0.87, 0.90), (0.78, 0.80, 0.84))
    """The two colours of the checkered floor."""
    floor_tile: float = 2.0
    """Edge of a floor tile, in voxels."""
    trace_color: RGB = (0.95, 0.45, 0.05)
    """Colour of the centre of mass's path."""
    trace_width: float = 2.0
    """Width of that path in (output) pixels."""
    view_radius: float = 2.5
    """Half-width of the world shown around the robot, in voxels beyond its own half-extent."""
    follow: bool = True
    """The camera follows the centre of mass horizontally (False: fixed, framing the whole trajectory)."""
    caption_size: int = 12
    """Font size of captions (output pixels)."""

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first field outside its allowed values."""
        if self.size < 16:
            raise ValueError(f"RenderConfig.size must be >= 16 pixels, got {self.size}")
        if self.supersample not in (1, 2, 3, 4):
            raise ValueError(f"RenderConfig.supersample must be one of 1, 2, 3, 4, got {self.supersample}")
        if self.frame not in ("grid", "body"):
            raise ValueError(f"RenderConfig.frame must be 'grid' or 'body', got {self.frame!r}")
        if not -90.0 < self.elevation < 90.0:
            raise ValueError(f"RenderConfig.elevation must be in (-90, 90) degrees, got {self.elevation}")
        if not 0.0 <= self.margin < 0.5:
            raise ValueError(f"RenderConfig.margin must be in [0, 0.5), got {self.margin}")
        if not self.material_colors:
            raise ValueError("RenderConfig.material_colors must hold at least one colour")
        if not self.floor_tile > 0:
            raise ValueError(f"RenderConfig.floor_tile must be > 0 voxels, got {self.floor_tile}")


# ------------------------------------------------------------------------------------------------ geometry

# The six face directions, in Voxelyze's slot order (X_POS, X_NEG, Y_POS, Y_NEG, Z_POS, Z_NEG).
FACE_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64)


def _face_corners() -> np.ndarray:
    """Corners of each face of the cube [-1, 1]³: float64 ``[6, 4, 3]``, counter-clockwise seen from outside."""
    corners = np.zeros((6, 4, 3))
    for d, n in enumerate(FACE_NORMALS):
        a = int(np.flatnonzero(n)[0])
        s = int(n[a])
        b, c = (a + 1) % 3, (a + 2) % 3  # e_b × e_c = e_a: (−,−), (+,−), (+,+), (−,+) turns about +e_a
        square = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        if s < 0:
            square = square[::-1]
        for k, (u, v) in enumerate(square):
            corners[d, k, a] = s
            corners[d, k, b] = u
            corners[d, k, c] = v
    return corners


FACE_CORNERS = _face_corners()


def _as_numpy_grid(x: torch.Tensor | np.ndarray, name: str, ndim: int) -> np.ndarray:
    """``x`` as a uint8 numpy array with ``ndim`` dimensions (``ValueError`` naming ``name`` otherwise)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu").numpy()
    x = np.asarray(x)
    if x.ndim != ndim:
        shape = "[X, Y, Z]" if ndim == 3 else "[N, X, Y, Z]"
        raise ValueError(f"{name} must be a {ndim}-d grid {shape} of material indices, got shape {x.shape}")
    if x.size and (x.min() < 0 or x.max() > 255):
        raise ValueError(f"{name} must hold material indices in 0..255, got values in [{x.min()}, {x.max()}]")
    return x.astype(np.uint8, copy=False)


def _exposed(solid: np.ndarray, blocker: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Cells of ``solid`` whose neighbour along ``direction`` is not in ``blocker`` (outside the grid counts as
    free): bool ``[X, Y, Z]``."""
    a = int(np.flatnonzero(direction)[0])
    s = int(direction[a])
    padded = np.pad(blocker, [(1, 1) if i == a else (0, 0) for i in range(3)])
    sl = [slice(None)] * 3
    sl[a] = slice(1 + s, 1 + s + blocker.shape[a])
    return solid & ~padded[tuple(sl)]


@dataclass
class _Camera:
    """Orthographic camera: ``towards`` points from the scene to the camera, ``right``/``up`` span the screen."""

    towards: np.ndarray
    right: np.ndarray
    up: np.ndarray

    @classmethod
    def from_config(cls, cfg: RenderConfig) -> _Camera:
        az, el = math.radians(cfg.azimuth), math.radians(cfg.elevation)
        towards = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        right = np.array([-math.sin(az), math.cos(az), 0.0])
        up = np.cross(right, -towards)
        return cls(towards, right, up)

    def screen(self, points: np.ndarray) -> np.ndarray:
        """World points ``[..., 3]`` → screen coordinates ``[..., 2]`` (x right, y up; world units)."""
        return np.stack([points @ self.right, points @ self.up], axis=-1)


def _shade(normals: np.ndarray, colors: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    """Lambert shading: float ``[Q, 3]`` colours of faces with unit ``normals [Q, 3]``."""
    light = np.asarray(cfg.light, dtype=np.float64)
    light = light / np.linalg.norm(light)
    k = cfg.ambient + cfg.diffuse * np.clip(normals @ light, 0.0, None)
    return np.clip(colors * k[:, None], 0.0, 1.0)


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1: a scalable built-in font
    except TypeError:  # older Pillow: the fixed bitmap font
        return ImageFont.load_default()


class _Canvas:
    """A supersampled Pillow image with a world→pixel projection; draws quads, lines and captions."""

    def __init__(self, cfg: RenderConfig, camera: _Camera, fit_points: np.ndarray) -> None:
        self.cfg, self.camera, self.ss = cfg, camera, cfg.supersample
        side = cfg.size * self.ss
        self.image = Image.new("RGB", (side, side), tuple(int(round(255 * c)) for c in cfg.background))
        self.draw = ImageDraw.Draw(self.image, "RGBA")  # "RGBA" draw mode alpha-blends fills onto the RGB image
        screen = camera.screen(fit_points.reshape(-1, 3))
        lo, hi = screen.min(axis=0), screen.max(axis=0)
        extent = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-12))
        self.scale = side * (1.0 - 2.0 * cfg.margin) / extent
        self.centre = (lo + hi) / 2.0
        self.side = side

    def pixels(self, points: np.ndarray) -> np.ndarray:
        """World points ``[..., 3]`` → (supersampled) pixel coordinates ``[..., 2]`` (y down)."""
        s = (self.camera.screen(points) - self.centre) * self.scale
        return np.stack([self.side / 2.0 + s[..., 0], self.side / 2.0 - s[..., 1]], axis=-1)

    def quads(self, corners: np.ndarray, rgb: np.ndarray, alpha: np.ndarray, outline: bool = True) -> None:
        """Fill quads ``corners [Q, 4, 3]`` (already in drawing order) with ``rgb [Q, 3]`` at opacity ``alpha [Q]``."""
        if len(corners) == 0:
            return
        pix = self.pixels(corners)  # [Q, 4, 2]
        onscreen = np.all((pix.max(axis=1) >= 0) & (pix.min(axis=1) <= self.side), axis=1)
        if not onscreen.all():  # skip what lies wholly outside the image (floor tiles mostly)
            pix, rgb, alpha = pix[onscreen], rgb[onscreen], alpha[onscreen]
        pts = pix.tolist()
        fill = np.concatenate([rgb, alpha[:, None]], axis=1)
        fills = [tuple(c) for c in np.rint(255 * fill).astype(int).tolist()]
        if outline and self.cfg.edge_darkening < 1.0:
            edge = np.concatenate([rgb * self.cfg.edge_darkening, np.minimum(1.0, alpha * 1.6)[:, None]], axis=1)
            edges: list[Any] = [tuple(c) for c in np.rint(255 * edge).astype(int).tolist()]
        else:
            edges = [None] * len(pts)
        width = max(1, self.ss // 2)
        draw = self.draw.polygon
        for p, f, e in zip(pts, fills, edges, strict=True):  # Pillow's C filler does the per-pixel work
            draw([tuple(q) for q in p], fill=f, outline=e, width=width)

    def floor_bounds(self, z: float) -> tuple[np.ndarray, np.ndarray] | None:
        """World (x, y) bounds ``(lo [2], hi [2])`` of the plane at height ``z`` seen in the image (None when the
        camera looks from below or along the plane)."""
        tz = float(self.camera.towards[2])
        if tz < 1e-3:
            return None
        half = self.side / 2.0 / self.scale
        pts = []
        for sx in (-half, half):
            for sy in (-half, half):
                s = self.centre + np.array([sx, sy])
                on_screen = s[0] * self.camera.right + s[1] * self.camera.up  # a point on the pixel's viewing ray
                t = (z - on_screen[2]) / tz
                pts.append((on_screen + t * self.camera.towards)[:2])
        arr = np.asarray(pts)
        return arr.min(axis=0), arr.max(axis=0)

    def polyline(self, points: np.ndarray, rgb: RGB, width: float) -> None:
        if len(points) < 2:
            return
        pts = [tuple(p) for p in self.pixels(points).tolist()]
        color = tuple(int(round(255 * c)) for c in rgb)
        self.draw.line(pts, fill=color, width=max(1, int(round(width * self.ss))), joint="curve")

    def dot(self, point: np.ndarray, rgb: RGB, radius: float) -> None:
        x, y = self.pixels(point[None])[0]
        r = radius * self.ss
        self.draw.ellipse([x - r, y - r, x + r, y + r], fill=tuple(int(round(255 * c)) for c in rgb))

    def finish(self, captions: Sequence[str] = ()) -> np.ndarray:
        """The image at output size, captions drawn (top-left, one per line): uint8 ``[H, W, 3]``."""
        image = self.image.reduce(self.ss) if self.ss > 1 else self.image
        if captions:
            draw = ImageDraw.Draw(image)
            font = _font(self.cfg.caption_size)
            draw.multiline_text((4, 3), "\n".join(captions), fill=(40, 40, 40), font=font, spacing=2)
        return np.asarray(image, dtype=np.uint8).copy()


# ------------------------------------------------------------------------------------------------ designs


def _material_rgb(materials: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    palette = np.asarray(cfg.material_colors, dtype=np.float64)
    return palette[(materials.astype(np.int64) - 1) % len(palette)]


def _grid_quads(
    grid: np.ndarray, body: np.ndarray, camera: _Camera, cfg: RenderConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The camera-facing exposed faces of a design, sorted back to front.

    Returns ``corners [Q, 4, 3]`` (voxel units, voxel (i, j, k) occupies [i, i+1]×[j, j+1]×[k, k+1]),
    ``rgb [Q, 3]`` shaded, ``alpha [Q]``, and ``kind [Q]`` (1 = body, 0 = removed voxel).
    """
    in_body = body > 0
    removed = (grid > 0) & ~in_body
    corners, rgb, alpha, kind, depth = [], [], [], [], []
    for d, n in enumerate(FACE_NORMALS):
        if float(n @ camera.towards) <= 1e-9:  # back faces of a closed surface are never seen
            continue
        for solid, is_body in ((in_body, True), (removed, False)):
            cells = np.argwhere(_exposed(solid, solid, n))
            if len(cells) == 0:
                continue
            quad = cells[:, None, :] + 0.5 + 0.5 * FACE_CORNERS[d][None]  # [q, 4, 3]
            if is_body:
                base = _material_rgb(body[tuple(cells.T)], cfg)
                a = np.ones(len(cells))
            else:
                base = np.broadcast_to(np.asarray(cfg.removed_color, dtype=np.float64), (len(cells), 3))
                a = np.full(len(cells), cfg.removed_alpha)
            corners.append(quad)
            rgb.append(_shade(np.broadcast_to(n.astype(np.float64), (len(cells), 3)), base, cfg))
            alpha.append(a)
            kind.append(np.full(len(cells), int(is_body)))
            depth.append(quad.mean(axis=1) @ camera.towards)
    if not corners:
        empty = np.zeros((0,))
        return np.zeros((0, 4, 3)), np.zeros((0, 3)), empty, empty.astype(np.int64)
    order = np.argsort(np.concatenate(depth), kind="stable")  # far (small towards-component) first
    return (np.concatenate(corners)[order], np.concatenate(rgb)[order], np.concatenate(alpha)[order],
            np.concatenate(kind)[order])


def _panes(shape: tuple[int, int, int], camera: _Camera) -> np.ndarray:
    """The three walls of the box [0, X]×[0, Y]×[0, Z] that face the camera from behind: ``[3, 4, 3]``."""
    size = np.asarray(shape, dtype=np.float64)
    walls = []
    for d, n in enumerate(FACE_NORMALS):
        if float(n @ camera.towards) < 0:  # outward normal away from the camera: a back wall (or the floor)
            walls.append((FACE_CORNERS[d] + 1.0) / 2.0 * size)
    return np.asarray(walls)


def render_grid(
    grid: torch.Tensor | np.ndarray,
    body: torch.Tensor | np.ndarray | None = None,
    config: RenderConfig | None = None,
    caption: str | Sequence[str] | None = None,
) -> np.ndarray:
    """Draw one design.

    grid: uint8 ``[X, Y, Z]`` material indices (0 = empty), the final grid of an episode.
    body: uint8 ``[X, Y, Z]``, the grid's body (its largest component, ``freeform.body``); voxels of ``grid``
        outside it are drawn translucent grey. None: every non-empty voxel is drawn as body.
    caption: text drawn in the top-left corner (a sequence: one line each).
    Returns RGB uint8 ``[size, size, 3]``.
    """
    cfg = config if config is not None else RenderConfig()
    cfg.validate()
    g = _as_numpy_grid(grid, "grid", 3)
    b = g if body is None else _as_numpy_grid(body, "body", 3)
    if b.shape != g.shape:
        raise ValueError(f"body must have the grid's shape {g.shape}, got {b.shape}")
    camera = _Camera.from_config(cfg)
    corners, rgb, alpha, _ = _grid_quads(g, b, camera, cfg)
    box = np.array([[i, j, k] for i in (0, g.shape[0]) for j in (0, g.shape[1]) for k in (0, g.shape[2])], float)
    if cfg.frame == "body" and len(corners):
        fit = corners
    else:
        fit = box
    canvas = _Canvas(cfg, camera, fit)
    if cfg.show_panes and cfg.frame == "grid":
        pane_rgb = np.tile(np.asarray(cfg.pane_color, dtype=np.float64), (3, 1))
        canvas.quads(_panes(g.shape, camera), pane_rgb, np.ones(3))
    canvas.quads(corners, rgb, alpha)
    lines = [caption] if isinstance(caption, str) else list(caption or [])
    return canvas.finish(lines)


def render_grids(
    grids: torch.Tensor | np.ndarray,
    bodies: torch.Tensor | np.ndarray | None = None,
    config: RenderConfig | None = None,
    captions: Sequence[str | Sequence[str]] | None = None,
) -> np.ndarray:
    """Draw a batch of designs: ``grids`` uint8 ``[N, X, Y, Z]`` (bodies likewise, or None) → RGB uint8
    ``[N, size, size, 3]``. ``captions``: one per design, or None."""
    g = _as_numpy_grid(grids, "grids", 4)
    b = None if bodies is None else _as_numpy_grid(bodies, "bodies", 4)
    if b is not None and b.shape != g.shape:
        raise ValueError(f"bodies must have the grids' shape {g.shape}, got {b.shape}")
    if captions is not None and len(captions) != len(g):
        raise ValueError(f"captions must hold one entry per grid ({len(g)}), got {len(captions)}")
    cfg = config if config is not None else RenderConfig()
    out = np.empty((len(g), cfg.size, cfg.size, 3), dtype=np.uint8)
    for i in range(len(g)):  # one image each: the rasteriser itself is vectorised over faces
        out[i] = render_grid(g[i], None if b is None else b[i], cfg, None if captions is None else captions[i])
    return out


def contact_sheet(
    images: np.ndarray | Sequence[np.ndarray], columns: int | None = None, gap: int = 4, background: int = 255
) -> np.ndarray:
    """Tile images ``[N, H, W, 3]`` into one sheet (row-major, ``columns`` wide; default ≈ √N): uint8 RGB."""
    imgs = np.asarray(images, dtype=np.uint8)
    if imgs.ndim != 4 or imgs.shape[-1] != 3 or len(imgs) == 0:
        raise ValueError(f"images must be a non-empty [N, H, W, 3] array, got shape {imgs.shape}")
    n, h, w, _ = imgs.shape
    cols = columns if columns is not None else math.ceil(math.sqrt(n))
    if cols < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    rows = math.ceil(n / cols)
    sheet = np.full((rows * h + (rows + 1) * gap, cols * w + (cols + 1) * gap, 3), background, dtype=np.uint8)
    for i in range(n):
        r, c = divmod(i, cols)
        y, x = gap + r * (h + gap), gap + c * (w + gap)
        sheet[y:y + h, x:x + w] = imgs[i]
    return sheet


# ------------------------------------------------------------------------------------------------ gaits


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


def _check_recording(recording: Recording, robot: int) -> None:
    n_bodies = len(recording.positions)
    if not 0 <= robot < n_bodies:
        raise ValueError(f"robot must be in 0..{n_bodies - 1} (bodies in the recording), got {robot}")
    if len(recording.times) == 0:
        raise ValueError("recording has no frames (simulate with record_every set)")
    if recording.positions[robot].shape[1] == 0:
        raise ValueError(f"robot {robot} has no voxels in the recording (an empty body is not simulated)")


def com_trajectory(recording: Recording, robot: int = 0) -> np.ndarray:
    """Centre of mass of ``robot`` in every frame: float64 ``[F, 3]`` metres (voxel mean: the paper's materials
    share one density, so every voxel has the same mass)."""
    _check_recording(recording, robot)
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
    _check_recording(recording, robot)
    L = float(recording.voxel_size)
    pos = recording.positions[robot].astype(np.float64)  # [F, n, 3]
    ori = recording.orientations[robot].astype(np.float64)  # [F, n, 4]
    n_frames = len(recording.times)
    chosen = np.arange(n_frames) if frames is None else np.asarray(frames, dtype=np.int64)
    if chosen.size and (chosen.min() < -n_frames or chosen.max() >= n_frames):
        raise ValueError(f"frames must index 0..{n_frames - 1}, got {chosen.tolist()}")
    covered = _covered_faces(np.asarray(recording.lattice[robot]))  # [n, 6]
    base = _material_rgb(np.asarray(recording.materials[robot]), cfg)  # [n, 3]
    camera = _Camera.from_config(cfg)
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
        canvas = _Canvas(cfg, camera, box)

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
        rgb = _shade(normals[vi, di], base[vi], cfg)
        order = np.argsort(corners.mean(axis=1) @ camera.towards, kind="stable")
        canvas.quads(corners[order], rgb[order], np.ones(len(order)))

        lines: list[str] = []
        if caption:
            disp = float(np.linalg.norm(com[f, :2] - start[:2])) / L
            lines = [f"t = {recording.times[f]:.2f} s", f"COM moved {disp:.2f} voxels"]
        out[i] = canvas.finish(lines)
    return out


# ------------------------------------------------------------------------------------------------ files


def _check_frames(frames: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3 or len(arr) == 0:
        raise ValueError(f"frames must be a non-empty [F, H, W, 3] uint8 array, got shape {arr.shape}")
    return arr.astype(np.uint8, copy=False)


def encode_gif(frames: np.ndarray | Sequence[np.ndarray], fps: float = 20.0) -> bytes:
    """Frames ``[F, H, W, 3]`` uint8 → the bytes of a looping animated GIF at ``fps`` frames per second."""
    arr = _check_frames(frames)
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    # One shared palette (quantised from a strip of frames) keeps colours from flickering between frames.
    strip = Image.fromarray(np.concatenate(list(arr[:: max(1, len(arr) // 8)]), axis=0))
    palette = strip.quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in arr]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], loop=0,
                   duration=max(20, int(round(1000.0 / fps))), disposal=1)
    return buf.getvalue()


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an RGB uint8 ``[H, W, 3]`` image as PNG; returns the path."""
    arr = np.asarray(image, dtype=np.uint8)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"image must be [H, W, 3] uint8, got shape {arr.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path, format="PNG", optimize=True)
    return path


def write_video(path: str | Path, frames: np.ndarray | Sequence[np.ndarray], fps: float = 20.0) -> Path:
    """Write frames ``[F, H, W, 3]`` uint8 as ``.gif`` (Pillow) or ``.mp4`` (H.264 through imageio-ffmpeg, the
    optional extra ``pip install 'freeform[video]'``, which ships its own ffmpeg); returns the path."""
    path = Path(path)
    arr = _check_frames(frames)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"video path must end in .gif or .mp4, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".gif":
        path.write_bytes(encode_gif(arr, fps))
        return path
    try:
        import imageio_ffmpeg
    except ImportError as exc:
        raise ValueError(
            "writing .mp4 needs imageio-ffmpeg: pip install 'freeform[video]' (or write a .gif)"
        ) from exc
    h, w = arr.shape[1:3]
    # H.264 with yuv420p wants even sizes; pad by one row/column of background when needed.
    ph, pw = h + h % 2, w + w % 2
    if (ph, pw) != (h, w):
        arr = np.pad(arr, ((0, 0), (0, ph - h), (0, pw - w), (0, 0)), mode="edge")
    writer = imageio_ffmpeg.write_frames(str(path), (pw, ph), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                         macro_block_size=1, output_params=["-loglevel", "error"])
    writer.send(None)  # prime the generator
    for f in arr:
        writer.send(np.ascontiguousarray(f))
    writer.close()
    return path


# ------------------------------------------------------------------------------------------------ TensorBoard


def add_gif(writer: SummaryWriter, tag: str, frames: np.ndarray, step: int, fps: float = 20.0) -> None:
    """Log an animated GIF as a TensorBoard image summary (TensorBoard's image tab plays it).

    This is what ``SummaryWriter.add_video`` does, minus its moviepy dependency (whose 2.x releases removed the
    ``moviepy.editor`` module that ``add_video`` imports, so it silently writes nothing).
    """
    from tensorboard.compat.proto.summary_pb2 import Summary

    arr = _check_frames(frames)
    image = Summary.Image(height=arr.shape[1], width=arr.shape[2], colorspace=3,
                          encoded_image_string=encode_gif(arr, fps))
    # SummaryWriter has no public way to add a prebuilt summary; add_video itself goes through this file writer.
    writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)


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


def pick_bodies(rewards: np.ndarray, rng: np.random.Generator) -> dict[str, int]:
    """Indices of the best, the median and a random design of an epoch (``rewards [E]``).

    The median is the lower middle element of the stable sort (ties keep episode order), so it is always an
    actual design rather than an interpolated reward.
    """
    r = np.asarray(rewards, dtype=np.float64).reshape(-1)
    if r.size == 0:
        raise ValueError("rewards must hold at least one episode")
    order = np.argsort(r, kind="stable")
    return {"best": int(np.argmax(r)), "median": int(order[(r.size - 1) // 2]), "random": int(rng.integers(r.size))}


def _bodies_of(final_grids: np.ndarray) -> np.ndarray:
    """The bodies (largest components) of ``final_grids`` via ``freeform.body``."""
    from freeform.body import largest_component  # the body owner's definition (spec: ties, 6-connectivity)

    out = largest_component(torch.from_numpy(np.ascontiguousarray(final_grids)))
    return out.detach().to("cpu").numpy().astype(np.uint8) if isinstance(out, torch.Tensor) else np.asarray(out)


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
    b = _as_numpy_grid(body, "body", 3)
    result = simulator.simulate(b[None], record_every=_frame_every(simulator, fps))
    if result.recording is None:
        raise ValueError("the simulator returned no recording")
    return result.recording


def log_epoch_renders(
    writer: SummaryWriter,
    final_grids: torch.Tensor | np.ndarray,
    bodies: torch.Tensor | np.ndarray | None,
    rewards: torch.Tensor | np.ndarray,
    step: int,
    rng: np.random.Generator | int | None = None,
    simulator: Simulator | None = None,
    config: RenderConfig | None = None,
    video: VideoConfig | None = None,
    prefix: str = "bodies",
) -> dict[str, int]:
    """Log one epoch's designs to TensorBoard at global step ``step``.

    Images ``<prefix>/best``, ``<prefix>/median``, ``<prefix>/random`` (each captioned with its reward) and, when
    a ``simulator`` is given (locomotion: one configured for a short run, e.g. burn_in 0 and duration
    ``video.seconds``), a GIF ``<prefix>/best_gait`` of the best robot. ``final_grids`` / ``bodies``: uint8
    ``[E, ρ, ρ, ρ]`` (bodies None: computed with ``freeform.body``); ``rewards [E]``. Returns the chosen indices.
    """
    grids = _as_numpy_grid(final_grids, "final_grids", 4)
    r = rewards.detach().to("cpu").numpy() if isinstance(rewards, torch.Tensor) else np.asarray(rewards)
    r = r.astype(np.float64).reshape(-1)
    if len(r) != len(grids):
        raise ValueError(f"rewards must hold one value per grid ({len(grids)}), got {len(r)}")
    b = _bodies_of(grids) if bodies is None else _as_numpy_grid(bodies, "bodies", 4)
    if b.shape != grids.shape:
        raise ValueError(f"bodies must have the grids' shape {grids.shape}, got {b.shape}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    chosen = pick_bodies(r, gen)
    cfg = config if config is not None else RenderConfig()
    for name, i in chosen.items():
        volume = int((b[i] > 0).sum())
        image = render_grid(grids[i], b[i], cfg, [f"{name} #{i}", f"reward {r[i]:.3g}", f"{volume} voxels"])
        writer.add_image(f"{prefix}/{name}", image, step, dataformats="HWC")
    if simulator is not None and (b[chosen["best"]] > 0).any():
        vid = video if video is not None else VideoConfig()
        recording = simulate_gait(simulator, b[chosen["best"]], vid.fps)
        frames = render_recording(recording, 0, replace(cfg, size=vid.size))
        add_gif(writer, f"{prefix}/best_gait", frames, step, vid.fps)
    writer.flush()
    return chosen


_GAIT_SIMULATORS: dict[Any, Simulator] = {}


def gait_simulator(sim_config: Any, seconds: float, arch: str = "auto") -> Simulator:
    """A ``Simulator`` of ``sim_config`` shortened to ``seconds`` from t = 0 (no burn-in), cached per settings."""
    from freeform.sim import Simulator

    short = replace(sim_config, burn_in=0.0, duration=float(seconds))
    key = (repr(short), arch)
    if key not in _GAIT_SIMULATORS:
        _GAIT_SIMULATORS[key] = Simulator(short, arch=arch)
    return _GAIT_SIMULATORS[key]


def log_bodies(writer: SummaryWriter, final_grids: Any, rewards: Any, step: int, cfg: Any) -> dict[str, int]:
    """The training loop's render hook: :func:`log_epoch_renders` configured from a ``TrainConfig``.

    The random pick is seeded by (run seed, step), so a resumed run logs the same bodies; a locomotion task gets
    the gait GIF of its best robot (simulated ``VideoConfig.seconds`` with the run's ``sim`` settings).
    """
    rng = np.random.default_rng([int(getattr(cfg, "seed", 0)), int(step)])
    simulator = None
    task = getattr(cfg, "task", None)
    if getattr(task, "name", None) == "locomotion":
        arch = str((getattr(task, "options", None) or {}).get("arch", "auto"))  # the task's own simulator device
        simulator = gait_simulator(cfg.sim, VideoConfig().seconds, arch)
    return log_epoch_renders(writer, final_grids, None, rewards, step, rng, simulator)


__all__ = [
    "FACE_CORNERS",
    "FACE_NORMALS",
    "PAPER_COLORS",
    "RenderConfig",
    "VideoConfig",
    "add_gif",
    "com_trajectory",
    "contact_sheet",
    "encode_gif",
    "gait_simulator",
    "log_bodies",
    "log_epoch_renders",
    "pick_bodies",
    "quat_to_matrix",
    "render_grid",
    "render_grids",
    "render_recording",
    "simulate_gait",
    "write_png",
    "write_video",
]

