"""Bodies from a user's file: a ``.npy`` of material grids, checked before anything is simulated or written.

A body is a uint8 grid ``[ρ, ρ, ρ]`` of material indices: 0 empty, 1 passive, 2 and 3 muscles in anti-phase (the
paper's materials; ``SimConfig.materials``). A file holds one body ``[ρ, ρ, ρ]`` or several ``[M, ρ, ρ, ρ]``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch


class BodyError(ValueError):
    """A bodies file that cannot be driven, with what is wrong and how to fix it."""


def read_bodies(path: str | Path, materials: int, who: str = "BODIES.npy") -> torch.Tensor:
    """The bodies of ``path`` as uint8 ``[M, ρ, ρ, ρ]`` in materials 0 … ``materials``. Refused with
    :class:`BodyError`, naming the body and the fix: a file that is no ``.npy`` of grids, a rank other than 3 or 4,
    grids that are not cubes, a float or other non-integer dtype, a material outside the range, an empty body. A
    body of several disconnected pieces is reduced to its largest 6-connected piece (the robot: the others would
    fall away from it), with a warning naming the body and the voxels dropped; no body is ever dropped."""
    from freeform.body import largest_component

    where = f"{who} {path}"
    try:
        grids = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise BodyError(f"{where}: not a .npy file of grids ({e}); save one with numpy.save(path, grids)") from e
    if grids.ndim not in (3, 4):
        raise BodyError(f"{where}: a body is a grid [ρ, ρ, ρ] and several are [M, ρ, ρ, ρ]; this array has rank "
                        f"{grids.ndim}, shape {list(grids.shape)}")
    grids = grids[None] if grids.ndim == 3 else grids
    if len(grids) == 0 or not grids.shape[1] == grids.shape[2] == grids.shape[3] or grids.shape[1] == 0:
        raise BodyError(f"{where}: grids must be non-empty cubes [M, ρ, ρ, ρ], got shape {list(grids.shape)} (pad a "
                        "body with zeros to a cube)")
    if not (np.issubdtype(grids.dtype, np.integer) or grids.dtype == np.bool_):
        raise BodyError(f"{where}: grids hold material indices, an integer dtype (uint8), and this one is "
                        f"{grids.dtype}: save grids.astype(numpy.uint8)")
    for i, grid in enumerate(grids):
        bad = np.unique(grid[(grid < 0) | (grid > materials)])
        if bad.size:
            raise BodyError(f"{where}: body {i} holds material {bad.tolist()}, and the materials are 0 (empty), "
                            f"1 (passive) … {materials}: set those voxels to one of them")
        if not grid.any():
            raise BodyError(f"{where}: body {i} is empty (no voxel: nothing to drive): give it voxels or leave it out "
                            "of the file")
    bodies = torch.from_numpy(grids.astype(np.uint8))
    kept = largest_component(bodies)
    dropped = ((bodies > 0).flatten(1).sum(1) - (kept > 0).flatten(1).sum(1)).tolist()
    for i, n in enumerate(dropped):
        if n:
            warnings.warn(f"{where}: body {i} is in several pieces; its largest 6-connected piece is kept and {n} "
                          "voxel(s) of the others dropped (they would fall away from it)", stacklevel=2)
    return kept


__all__ = ["BodyError", "read_bodies"]
