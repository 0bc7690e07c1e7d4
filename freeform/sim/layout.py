"""Bodies -> one flat voxel array and one flat link array for a whole batch (vectorised torch, no per-voxel loop).

Each non-empty body is cropped to its bounding box; its voxel (ix, iy, iz) starts at (ix, iy, iz)·L relative to
the robot's own origin, so the lowest layer (iz = 0) touches the floor (spec section 1). Voxels are ordered by
robot, then in C order of the cropped grid; links by robot, then axis, then C order of the negative voxel.
Every voxel lists its up to six links in fixed slots (X_POS, X_NEG, Y_POS, Y_NEG, Z_POS, Z_NEG; -1 = none), so
a voxel gathers its forces without atomics.

The ``Layout`` is also the low-level hook for tests and tools: ``fixed`` (all 6 DOF held, e.g. a cantilever
root), ``temp_base`` (a constant temperature added to the actuation), ``velocity`` (initial linear velocity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Layout:
    """Flattened batch. n = voxels, m = links, R = simulated (non-empty) robots, B = bodies passed in.

    robot_of_body: int64 [B], index into the simulated robots or -1 for an empty body.
    body_of_robot: int64 [R]. voxel_robot: int32 [n]. lattice: int32 [n, 3] index in the cropped body.
    material: int32 [n] (1-based material index). slots: int32 [n, 6] link index per direction or -1.
    link_neg / link_pos: int32 [m] voxel indices. link_axis: int32 [m] (0 = x, 1 = y, 2 = z).
    link_robot: int32 [m]. voxel_start / link_start: int64 [R + 1] offsets of each robot's range.
    fixed: bool [n]. temp_base: float64 [n]. velocity: float64 [n, 3] (m/s).
    origin: int32 [R, 3], each robot's crop origin in its body's grid: voxel v sits in cell
    ``lattice[v] + origin[voxel_robot[v]]`` of body ``body_of_robot[voxel_robot[v]]`` (what maps a controller's
    per-cell actions and observations back and forth).
    """

    robot_of_body: np.ndarray
    body_of_robot: np.ndarray
    voxel_robot: np.ndarray
    lattice: np.ndarray
    material: np.ndarray
    slots: np.ndarray
    link_neg: np.ndarray
    link_pos: np.ndarray
    link_axis: np.ndarray
    link_robot: np.ndarray
    voxel_start: np.ndarray
    link_start: np.ndarray
    fixed: np.ndarray
    temp_base: np.ndarray
    velocity: np.ndarray
    origin: np.ndarray

    @property
    def num_voxels(self) -> int:
        return int(self.material.shape[0])

    @property
    def num_links(self) -> int:
        return int(self.link_neg.shape[0])

    @property
    def num_robots(self) -> int:
        return int(self.body_of_robot.shape[0])

    @property
    def num_bodies(self) -> int:
        return int(self.robot_of_body.shape[0])


def validate_grids(grids: torch.Tensor | np.ndarray, num_materials: int) -> torch.Tensor:
    """Check ``grids`` (uint8 ``[B, X, Y, Z]`` material indices) and return it as a CPU uint8 tensor."""
    if isinstance(grids, np.ndarray):
        grids = torch.from_numpy(grids)
    if not isinstance(grids, torch.Tensor):
        raise ValueError(f"grids must be a torch.Tensor or np.ndarray, got {type(grids).__name__}")
    if grids.dtype != torch.uint8:
        raise ValueError(f"grids must have dtype uint8 (material indices), got {grids.dtype}")
    if grids.dim() != 4:
        raise ValueError(f"grids must have rank 4 [B, X, Y, Z], got shape {tuple(grids.shape)}")
    grids = grids.detach().cpu()
    if grids.numel() and int(grids.max()) > num_materials:
        raise ValueError(
            f"grids holds material index {int(grids.max())} but only materials 1..{num_materials} are configured "
            "(0 = empty)"
        )
    return grids


def _face_links(cells: tuple[torch.Tensor, ...], dims: tuple[int, ...]) -> tuple[torch.Tensor, ...]:
    """The links between face neighbours among the occupied ``cells = (b, x, y, z)`` (each ``[n]``, in C order) of
    grids ``[B, *dims]``: (negative voxel, positive voxel, axis) ``[m]`` each, by axis, then in C order of their
    negative voxel.

    Face neighbours are found by binary search in the sorted flat indices of the occupied cells (no dense
    ``[B, X, Y, Z]`` index grid: the batch's voxels are a few percent of its cells). nonzero() lists cells in C
    order, so ``flat`` is sorted and the links of each axis come out in C order of their negative voxel."""
    b, x, y, z = cells
    n = int(b.numel())
    strides = (dims[1] * dims[2], dims[2], 1)
    flat = ((b * dims[0] + x) * dims[1] + y) * dims[2] + z
    negs, poss, axes = [], [], []
    for axis, coord in enumerate((x, y, z)):
        has_next = coord < dims[axis] - 1
        cand = torch.nonzero(has_next).flatten()
        target = flat[cand] + strides[axis]
        at = torch.searchsorted(flat, target).clamp_max(max(n - 1, 0))
        hit = flat[at] == target if n else torch.zeros(0, dtype=torch.bool)
        negs.append(cand[hit])
        poss.append(at[hit])
        axes.append(torch.full((int(hit.sum()),), axis, dtype=torch.int64))
    return torch.cat(negs), torch.cat(poss), torch.cat(axes)


def build_layout(grids: torch.Tensor | np.ndarray, num_materials: int) -> Layout:
    """Flatten a batch of bodies (uint8 ``[B, X, Y, Z]``, 0 = empty) into a ``Layout``."""
    grids = validate_grids(grids, num_materials)
    B = grids.shape[0]
    occupied = grids > 0
    nonempty = occupied.flatten(1).any(dim=1) if B else torch.zeros(0, dtype=torch.bool)
    body_of_robot = torch.nonzero(nonempty).flatten()
    R = int(body_of_robot.numel())
    robot_of_body = torch.full((B,), -1, dtype=torch.int64)
    robot_of_body[body_of_robot] = torch.arange(R)

    b, x, y, z = torch.nonzero(occupied, as_tuple=True)  # C order: body, then x slowest, z fastest
    voxel_robot = robot_of_body[b]
    n = int(b.numel())
    material = grids[b, x, y, z].to(torch.int32)
    # crop each body to its bounding box: subtract the per-robot minimum of every axis
    xyz = torch.stack([x, y, z], dim=1)
    lo = torch.full((max(R, 1), 3), torch.iinfo(torch.int64).max, dtype=torch.int64)
    lo = lo.scatter_reduce(0, voxel_robot[:, None].expand(-1, 3), xyz, reduce="amin", include_self=True)
    lattice = xyz - lo[voxel_robot]

    link_neg, link_pos, link_axis = _face_links((b, x, y, z), tuple(grids.shape[1:]))
    # group links by robot (stable, so axis-major order inside a robot is kept)
    link_robot = voxel_robot[link_neg] if n else torch.zeros(0, dtype=torch.int64)
    order = torch.sort(link_robot, stable=True).indices
    link_neg, link_pos, link_axis, link_robot = link_neg[order], link_pos[order], link_axis[order], link_robot[order]
    m = int(link_neg.numel())

    slots = torch.full((n, 6), -1, dtype=torch.int64)
    lid = torch.arange(m)
    slots[link_neg, 2 * link_axis] = lid  # the link leaves the negative voxel in its +axis direction
    slots[link_pos, 2 * link_axis + 1] = lid

    def starts(owner: torch.Tensor) -> np.ndarray:
        counts = torch.bincount(owner, minlength=R) if owner.numel() else torch.zeros(R, dtype=torch.int64)
        return torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(counts, 0)]).numpy()

    return Layout(
        robot_of_body=robot_of_body.numpy(),
        body_of_robot=body_of_robot.numpy(),
        voxel_robot=voxel_robot.to(torch.int32).numpy(),
        lattice=lattice.to(torch.int32).numpy(),
        material=material.numpy(),
        slots=slots.to(torch.int32).numpy(),
        link_neg=link_neg.to(torch.int32).numpy(),
        link_pos=link_pos.to(torch.int32).numpy(),
        link_axis=link_axis.to(torch.int32).numpy(),
        link_robot=link_robot.to(torch.int32).numpy(),
        voxel_start=starts(voxel_robot),
        link_start=starts(link_robot),
        fixed=np.zeros(n, dtype=bool),
        temp_base=np.zeros(n),
        velocity=np.zeros((n, 3)),
        origin=lo[:R].to(torch.int32).numpy(),
    )
