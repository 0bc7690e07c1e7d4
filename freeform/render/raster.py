"""The shaded voxel rasteriser every picture is drawn with: an orthographic camera, Lambert shading and a
Pillow canvas.

The visible faces of a scene arrive as one numpy array of quads already sorted back to front (painter's algorithm —
exact enough for unit cubes on a grid, and for the slightly rotated cubes of a gait), are shaded with one
directional light, and filled with Pillow's C polygon filler at twice the size, then box-filtered down
(anti-aliasing). Pillow is already installed as a dependency of TensorBoard; no GL context is needed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from freeform.surface import PAPER_COLORS, RGB


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


@dataclass
class Camera:
    """Orthographic camera: ``towards`` points from the scene to the camera, ``right``/``up`` span the screen."""

    towards: np.ndarray
    right: np.ndarray
    up: np.ndarray

    @classmethod
    def from_config(cls, cfg: RenderConfig) -> Camera:
        az, el = math.radians(cfg.azimuth), math.radians(cfg.elevation)
        towards = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        right = np.array([-math.sin(az), math.cos(az), 0.0])
        up = np.cross(right, -towards)
        return cls(towards, right, up)

    def screen(self, points: np.ndarray) -> np.ndarray:
        """World points ``[..., 3]`` → screen coordinates ``[..., 2]`` (x right, y up; world units)."""
        return np.stack([points @ self.right, points @ self.up], axis=-1)


def lambert(normals: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    """Brightness ``[Q]`` of faces with unit ``normals [Q, 3]``: ambient + diffuse · max(0, n·light)."""
    light = np.asarray(cfg.light, dtype=np.float64)
    light = light / np.linalg.norm(light)
    return cfg.ambient + cfg.diffuse * np.clip(normals @ light, 0.0, None)


def shade(normals: np.ndarray, colors: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    """Lambert shading: float ``[Q, 3]`` colours of faces with unit ``normals [Q, 3]``."""
    return np.clip(colors * lambert(normals, cfg)[:, None], 0.0, 1.0)


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1: a scalable built-in font
    except TypeError:  # older Pillow: the fixed bitmap font
        return ImageFont.load_default()


class Canvas:
    """A supersampled Pillow image with a world→pixel projection; draws quads, lines and captions."""

    def __init__(self, cfg: RenderConfig, camera: Camera, fit_points: np.ndarray) -> None:
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


__all__ = ["Camera", "Canvas", "RenderConfig", "lambert", "shade"]
