"""What ``freeform.render`` and ``freeform.io`` both read: the faces of a voxel, the paper's material colours, and
the checks on grids and recordings they share.

Kept apart from both so that an export (``io``) never needs the rasteriser, and the two cannot drift on which
face is which, which corner order is outward, or which colour a material has.

Grids are uint8 ``[X, Y, Z]`` material indices (0 = empty), z up; voxel (i, j, k) fills [i, i+1]×[j, j+1]×[k, k+1].
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from freeform.sim import Recording

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


MATERIAL_NAMES = ("Passive", "MuscleA", "MuscleB")
"""Palette names of materials 1-3 in exported files (the paper's passive tissue and two muscles)."""


def material_name(m: int) -> str:
    """The name of material index ``m`` (>= 1) in an exported file."""
    return MATERIAL_NAMES[m - 1] if m - 1 < len(MATERIAL_NAMES) else f"Material{m}"


def material_rgb(materials: np.ndarray | int, palette: tuple[RGB, ...] = PAPER_COLORS) -> np.ndarray:
    """Colours of material indices (>= 1) ``[...]``: float64 ``[..., 3]``; the palette repeats past its end."""
    p = np.asarray(palette, dtype=np.float64)
    return p[(np.asarray(materials).astype(np.int64) - 1) % len(p)]


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


def as_grid(x: torch.Tensor | np.ndarray, name: str, ndim: int) -> np.ndarray:
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


def exposed(solid: np.ndarray, blocker: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Cells of ``solid`` whose neighbour along ``direction`` is not in ``blocker`` (outside the grid counts as
    free): bool ``[X, Y, Z]``."""
    a = int(np.flatnonzero(direction)[0])
    s = int(direction[a])
    padded = np.pad(blocker, [(1, 1) if i == a else (0, 0) for i in range(3)])
    sl = [slice(None)] * 3
    sl[a] = slice(1 + s, 1 + s + blocker.shape[a])
    return solid & ~padded[tuple(sl)]


def check_recording(recording: Recording, robot: int) -> None:
    """Raise ``ValueError`` unless robot ``robot`` of ``recording`` has frames and voxels to draw or export."""
    n_bodies = len(recording.positions)
    if not 0 <= robot < n_bodies:
        raise ValueError(f"robot must be in 0..{n_bodies - 1} (bodies in the recording), got {robot}")
    if len(recording.times) == 0:
        raise ValueError("recording has no frames (simulate with record_every set)")
    if recording.positions[robot].shape[1] == 0:
        raise ValueError(f"robot {robot} has no voxels in the recording (an empty body is not simulated)")


__all__ = [
    "FACE_CORNERS",
    "FACE_NORMALS",
    "PAPER_COLORS",
    "RGB",
    "as_grid",
    "check_recording",
    "exposed",
    "material_name",
    "material_rgb",
    "MATERIAL_NAMES",
]
