"""Design images: one final grid (its body in the paper's colours, the rest translucent grey), a batch of them,
and a contact sheet of many.

The removed voxels (those of the final grid outside the body) can never touch the body face to face — they would
be part of it — so the faces of the two are culled independently.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from freeform.render.raster import Camera, Canvas, RenderConfig, shade
from freeform.surface import FACE_CORNERS, FACE_NORMALS, as_grid, exposed, material_rgb


def _grid_quads(
    grid: np.ndarray, body: np.ndarray, camera: Camera, cfg: RenderConfig
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
            cells = np.argwhere(exposed(solid, solid, n))
            if len(cells) == 0:
                continue
            quad = cells[:, None, :] + 0.5 + 0.5 * FACE_CORNERS[d][None]  # [q, 4, 3]
            if is_body:
                base = material_rgb(body[tuple(cells.T)], cfg.material_colors)
                a = np.ones(len(cells))
            else:
                base = np.broadcast_to(np.asarray(cfg.removed_color, dtype=np.float64), (len(cells), 3))
                a = np.full(len(cells), cfg.removed_alpha)
            corners.append(quad)
            rgb.append(shade(np.broadcast_to(n.astype(np.float64), (len(cells), 3)), base, cfg))
            alpha.append(a)
            kind.append(np.full(len(cells), int(is_body)))
            depth.append(quad.mean(axis=1) @ camera.towards)
    if not corners:
        empty = np.zeros((0,))
        return np.zeros((0, 4, 3)), np.zeros((0, 3)), empty, empty.astype(np.int64)
    order = np.argsort(np.concatenate(depth), kind="stable")  # far (small towards-component) first
    return (np.concatenate(corners)[order], np.concatenate(rgb)[order], np.concatenate(alpha)[order],
            np.concatenate(kind)[order])


def _panes(shape: tuple[int, int, int], camera: Camera) -> np.ndarray:
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
    g = as_grid(grid, "grid", 3)
    b = g if body is None else as_grid(body, "body", 3)
    if b.shape != g.shape:
        raise ValueError(f"body must have the grid's shape {g.shape}, got {b.shape}")
    camera = Camera.from_config(cfg)
    corners, rgb, alpha, _ = _grid_quads(g, b, camera, cfg)
    box = np.array([[i, j, k] for i in (0, g.shape[0]) for j in (0, g.shape[1]) for k in (0, g.shape[2])], float)
    if cfg.frame == "body" and len(corners):
        fit = corners
    else:
        fit = box
    canvas = Canvas(cfg, camera, fit)
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
    g = as_grid(grids, "grids", 4)
    b = None if bodies is None else as_grid(bodies, "bodies", 4)
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


__all__ = ["contact_sheet", "render_grid", "render_grids"]
