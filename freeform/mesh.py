"""Meshes of voxel bodies: the outer surface as one welded, watertight triangle mesh (:func:`voxel_mesh`), written
as OBJ or STL, and MagicaVoxel's ``.vox`` (``freeform.io`` exports every format; docstrings there).

Grids are uint8 ``[X, Y, Z]`` material indices (0 = empty), z up, as everywhere in freeform.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from freeform.surface import (
    FACE_CORNERS,
    FACE_NORMALS,
    PAPER_COLORS,
    RGB,
    as_grid,
    exposed,
    material_name,
    material_rgb,
)


@dataclass
class Mesh:
    """A triangle mesh: ``vertices [V, 3]`` float64, ``faces [T, 3]`` int64 (counter-clockwise seen from
    outside), ``materials [T]`` uint8 (the voxel each triangle bounds)."""

    vertices: np.ndarray
    faces: np.ndarray
    materials: np.ndarray

    def signed_volume(self) -> float:
        """Σ v0·(v1 × v2) / 6 over the triangles: the enclosed volume of a closed, outward-oriented mesh."""
        v = self.vertices[self.faces]  # [T, 3, 3]
        return float(np.einsum("ti,ti->t", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def _split_pinched_edges(quads: np.ndarray, cells: np.ndarray, points: np.ndarray, vertices: list[np.ndarray]
                         ) -> tuple[dict[int, list[tuple[int, int]]], int]:
    """Edges used by four faces (``quads [Q, 4]`` welded vertex ids of faces of the voxels ``cells [Q, 3]``, at
    ``points [V, 3]``): pair the faces by voxel and split the second voxel's pair off at a midpoint, appended to
    ``vertices``. Returns each split quad's ``[(slot, midpoint vertex)]`` and the next free vertex id."""
    next_id = len(points)
    a, b = quads, np.roll(quads, -1, axis=1)
    keys = np.sort(np.stack([a, b], axis=-1), axis=-1).reshape(-1, 2)  # [Q·4, 2], slot s of quad q at q·4 + s
    _, edge_id, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    edge_id = edge_id.reshape(-1)
    inserted: dict[int, list[tuple[int, int]]] = {}  # quad -> [(slot, midpoint vertex)]
    for e in np.flatnonzero(counts == 4).tolist():  # rare: a short loop over the pinched edges only
        uses = np.flatnonzero(edge_id == e)
        q_of, slot_of = uses // 4, uses % 4
        owners = cells[q_of]
        second = np.any(owners != owners[np.lexsort(owners.T[::-1])[0]], axis=1)  # the later voxel's two faces
        lo, hi = keys[uses[0]]
        vertices.append(((points[lo] + points[hi]) / 2.0)[None])
        for q, s in zip(q_of[second].tolist(), slot_of[second].tolist(), strict=True):
            inserted.setdefault(q, []).append((s, next_id))
        next_id += 1
    if np.any((counts != 2) & (counts != 4)):  # cannot happen for a voxel surface; guard the invariant
        raise ValueError("internal error: a voxel surface edge is used by an odd number of faces")
    return inserted, next_id


def voxel_mesh(body: torch.Tensor | np.ndarray, voxel_size: float = 1.0) -> Mesh:
    """The outer surface of ``body`` (uint8 ``[X, Y, Z]``): voxel (i, j, k) fills [i, i+1]×[j, j+1]×[k, k+1]·L.

    Faces between two voxels (of any materials) are dropped; every face between a voxel and an empty cell is
    two triangles. Vertices are welded, so the mesh is one indexed surface. Where two voxels meet only along an
    edge (diagonal neighbours with both other cells around the edge empty, which a 6-connected body can contain)
    four faces share that edge; to keep every edge shared by exactly two triangles, the second voxel's two faces
    get their own vertex at the edge's midpoint and are fanned from their centres — the surface pinches apart
    there instead of crossing itself, and the enclosed volume is unchanged.
    """
    g = as_grid(body, "body", 3)
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    solid = g > 0
    offsets = np.rint((FACE_CORNERS + 1.0) / 2.0).astype(np.int64)  # unit-cube corners of each face, CCW outside
    cells_l, corners_l, mats_l = [], [], []
    for d, n in enumerate(FACE_NORMALS):
        cells = np.argwhere(exposed(solid, solid, n))
        cells_l.append(cells)
        corners_l.append(cells[:, None, :] + offsets[d][None])
        mats_l.append(g[tuple(cells.T)])
    cells = np.concatenate(cells_l)  # [Q, 3] the voxel behind each face
    corners = np.concatenate(corners_l)  # [Q, 4, 3] integer lattice points
    mats = np.concatenate(mats_l)
    if len(cells) == 0:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.uint8))
    points, inverse = np.unique(corners.reshape(-1, 3), axis=0, return_inverse=True)
    quads = inverse.reshape(-1, 4)  # [Q, 4] welded vertex ids
    vertices = [points.astype(np.float64)]

    inserted, next_id = _split_pinched_edges(quads, cells, points, vertices)
    plain = np.array([q for q in range(len(quads)) if q not in inserted], dtype=np.int64)
    tri = [quads[plain][:, [0, 1, 2]], quads[plain][:, [0, 2, 3]]]
    tri_mats = [mats[plain], mats[plain]]
    for q, mids in inserted.items():
        ring: list[int] = []
        slots = dict(mids)
        for s in range(4):
            ring.append(int(quads[q, s]))
            if s in slots:
                ring.append(slots[s])
        vertices.append(points[quads[q]].mean(axis=0)[None].astype(np.float64))
        centre = next_id
        next_id += 1
        fan = np.array([[centre, ring[i], ring[(i + 1) % len(ring)]] for i in range(len(ring))], dtype=np.int64)
        tri.append(fan)
        tri_mats.append(np.full(len(fan), mats[q]))
    return Mesh(np.concatenate(vertices) * voxel_size, np.concatenate(tri).astype(np.int64),
                np.concatenate(tri_mats).astype(np.uint8))


def write_obj(path: str | Path, body: torch.Tensor | np.ndarray, voxel_size: float = 1.0,
              colors: tuple[RGB, ...] = PAPER_COLORS) -> Path:
    """Write the surface of ``body`` as Wavefront OBJ with a ``.mtl`` beside it (one material per voxel
    material, in the paper's colours); returns the OBJ's path."""
    path = Path(path)
    mesh = voxel_mesh(body, voxel_size)
    path.parent.mkdir(parents=True, exist_ok=True)
    mtl = path.with_suffix(".mtl")
    used = sorted({int(m) for m in mesh.materials})
    kd = {m: " ".join(f"{c:.4f}" for c in material_rgb(m, colors)) for m in used}
    mtl.write_text("".join(f"newmtl {material_name(m)}\nKd {kd[m]}\nKa 0 0 0\nd 1\n\n" for m in used),
                   encoding="ascii")
    lines = [f"# freeform voxel body: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles",
             f"mtllib {mtl.name}", "o body"]
    lines += [f"v {x:.6g} {y:.6g} {z:.6g}" for x, y, z in mesh.vertices.tolist()]
    for m in used:
        lines.append(f"usemtl {material_name(m)}")
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces[mesh.materials == m].tolist()]
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path


def write_stl(path: str | Path, body: torch.Tensor | np.ndarray, voxel_size: float = 1.0) -> Path:
    """Write the surface of ``body`` as binary STL (units: those of ``voxel_size``); returns the path."""
    path = Path(path)
    mesh = voxel_mesh(body, voxel_size)
    v = mesh.vertices[mesh.faces]  # [T, 3, 3]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    record = np.zeros(len(v), dtype=[("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    record["normal"], record["v"] = normal, v
    path.parent.mkdir(parents=True, exist_ok=True)
    header = b"freeform voxel body (binary STL)".ljust(80, b" ")
    path.write_bytes(header + struct.pack("<I", len(v)) + record.tobytes())
    return path


def read_stl(path: str | Path) -> np.ndarray:
    """Triangles of a binary STL: float32 ``[T, 3, 3]``."""
    data = Path(path).read_bytes()
    (n,) = struct.unpack_from("<I", data, 80)
    record = np.frombuffer(data, dtype=[("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")], count=n,
                           offset=84)
    return record["v"].copy()


# ------------------------------------------------------------------------------------------------ MagicaVoxel


def _chunk(tag: bytes, content: bytes, children: bytes = b"") -> bytes:
    return tag + struct.pack("<ii", len(content), len(children)) + content + children


def write_vox(path: str | Path, body: torch.Tensor | np.ndarray, colors: tuple[RGB, ...] = PAPER_COLORS) -> Path:
    """Write ``body`` as a MagicaVoxel ``.vox`` (version 150): colour index = material, palette entries 1..
    coloured as the paper's materials; returns the path."""
    g = as_grid(body, "body", 3)
    if max(g.shape) > 256:
        raise ValueError(f".vox models are at most 256 voxels on a side, got {g.shape}")
    cells = np.argwhere(g > 0)
    xyzi = np.concatenate([cells, g[tuple(cells.T)][:, None]], axis=1).astype(np.uint8)
    palette = np.full((256, 4), 200, dtype=np.uint8)
    palette[:, 3] = 255
    palette[:255, :3] = np.rint(255 * material_rgb(np.arange(1, 256), colors))  # RGBA entry i: colour index i + 1
    size = _chunk(b"SIZE", struct.pack("<iii", *g.shape))
    voxels = _chunk(b"XYZI", struct.pack("<i", len(cells)) + xyzi.tobytes())
    rgba = _chunk(b"RGBA", palette.tobytes())
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"VOX " + struct.pack("<i", 150) + _chunk(b"MAIN", b"", size + voxels + rgba))
    return path


def read_vox(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The first model of a ``.vox`` file: grid uint8 ``[X, Y, Z]`` of colour indices, palette uint8 ``[256, 4]``
    (row i = colour index i + 1)."""
    data = Path(path).read_bytes()
    if data[:4] != b"VOX ":
        raise ValueError(f"{path} is not a MagicaVoxel file (no 'VOX ' magic)")
    if data[8:12] != b"MAIN":
        raise ValueError(f"{path} lacks the MAIN chunk")
    offset, end = 20 + struct.unpack_from("<i", data, 12)[0], len(data)
    shape, grid, palette = None, None, None
    while offset < end:
        tag = data[offset:offset + 4]
        n_content, n_children = struct.unpack_from("<ii", data, offset + 4)
        body = data[offset + 12:offset + 12 + n_content]
        if tag == b"SIZE" and shape is None:
            shape = struct.unpack_from("<iii", body)
        elif tag == b"XYZI" and grid is None:
            if shape is None:
                raise ValueError(f"{path}: XYZI chunk before SIZE")
            (count,) = struct.unpack_from("<i", body)
            xyzi = np.frombuffer(body, dtype=np.uint8, count=4 * count, offset=4).reshape(count, 4)
            grid = np.zeros(shape, dtype=np.uint8)
            grid[xyzi[:, 0], xyzi[:, 1], xyzi[:, 2]] = xyzi[:, 3]
        elif tag == b"RGBA":
            palette = np.frombuffer(body, dtype=np.uint8).reshape(256, 4).copy()
        offset += 12 + n_content + n_children
    if grid is None:
        raise ValueError(f"{path} holds no model (SIZE + XYZI)")
    return grid, palette if palette is not None else np.zeros((256, 4), np.uint8)


__all__ = ["Mesh", "read_stl", "read_vox", "voxel_mesh", "write_obj", "write_stl", "write_vox"]
