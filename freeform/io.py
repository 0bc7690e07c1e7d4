"""Exporting robots to other tools: voxcraft (VXD + VXA, ``.history``), meshes (OBJ, STL) and MagicaVoxel (``.vox``).

- **VXD / VXA** (voxcraft-sim, voxcraft-viz, the paper's simulator). A VXA holds the simulation settings and the
  material palette; a VXD holds one body and *replaces* the VXA's structure (``replace="VXA.VXC.Structure"``).
  The structure is ``X/Y/Z_Voxels`` plus one ``<Layer>`` per z, each a CDATA string of one character per cell
  with x varying fastest, then y (``ASCII_READABLE``: material index + ``'0'``). Each voxel's actuation phase is
  written as the VXD's ``<PhaseOffset>`` layers (comma-separated, in cycles) because voxcraft-sim ignores the
  palette's ``MaterialTempPhase`` (spec ``physics.md`` section 4). :func:`read_vxd` parses the structure back.
- **``.history``** (voxcraft-viz replays it). Text: ``{{{setting}}}`` lines (``<rescale>``, ``<matcolor>``,
  ``<voxel_size>``), then one line per frame ``<<<Step<i> Time:<t>>>>`` followed by one record per voxel
  ``x,y,z,angle,ax,ay,az,nx,ny,nz,px,py,pz,material,signal,;`` and ``<<<>>>``. Positions and the corner offsets
  ``n``/``p`` are metres divided by ``rescale``; ``angle`` (degrees) and the unit axis ``a`` are the voxel's
  rotation (the viewer hands them to ``glRotated``). :func:`read_history` parses it back.
- **OBJ / STL**: the body's outer surface — the faces between a voxel and an empty cell (cavity walls included),
  welded into one indexed mesh whose every edge is shared by exactly two triangles (watertight, consistently
  oriented outwards), ready for a slicer or Blender. See :func:`voxel_mesh` for the one subtle case.
- **``.vox``** (MagicaVoxel 150): ``VOX `` chunks ``MAIN`` > ``SIZE``, ``XYZI``, ``RGBA``; colour index = material.

Grids are uint8 ``[X, Y, Z]`` material indices (0 = empty), z up, as everywhere in freeform.
"""

from __future__ import annotations

import math
import re
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from freeform.body import crop as crop_to_bounding_box
from freeform.surface import (
    FACE_CORNERS,
    FACE_NORMALS,
    PAPER_COLORS,
    RGB,
    as_grid,
    check_recording,
    exposed,
    material_rgb,
)

if TYPE_CHECKING:
    from freeform.sim import Recording, SimConfig

MATERIAL_NAMES = ("Passive", "MuscleA", "MuscleB")
"""Palette names of materials 1-3 in exported files (the paper's passive tissue and two muscles)."""


def _default_sim_config() -> SimConfig:
    from freeform.sim import SimConfig

    return SimConfig()


def _crop(grid: np.ndarray) -> np.ndarray:
    """The grid cut to its bounding box (``freeform.body.crop``), so the lowest layer touches the floor as the
    simulator places a body; an empty body is an error here, since the file would hold nothing."""
    if not grid.any():
        raise ValueError("body is empty: nothing to export")
    return crop_to_bounding_box(torch.from_numpy(np.ascontiguousarray(grid))).numpy()


def _material_name(m: int) -> str:
    return MATERIAL_NAMES[m - 1] if m - 1 < len(MATERIAL_NAMES) else f"Material{m}"


# ------------------------------------------------------------------------------------------------ VXD / VXA


def _layers(values: np.ndarray, fmt) -> list[str]:
    """One string per z layer; cells in voxcraft's order (x fastest, then y)."""
    return [fmt(values[:, :, z].T.reshape(-1)) for z in range(values.shape[2])]


def vxd_string(body: torch.Tensor | np.ndarray, sim_config: SimConfig | None = None, crop: bool = True) -> str:
    """The VXD text of ``body`` (uint8 ``[X, Y, Z]``); ``crop``: cut to its bounding box first, as the simulator
    does, so the lowest layer rests on the floor. Phase offsets come from ``sim_config.materials`` (default: the
    paper's)."""
    g = as_grid(body, "body", 3)
    if crop:
        g = _crop(g)
    if g.max(initial=0) > 74:  # ASCII_READABLE: '0' + index must stay a printable, non-markup character
        raise ValueError(f"body holds material {int(g.max())}; VXD's ASCII_READABLE structure allows 0..74")
    cfg = sim_config if sim_config is not None else _default_sim_config()
    phases = np.zeros(256)
    for i, m in enumerate(cfg.materials, start=1):
        phases[i] = m.phase
    if g.max(initial=0) > len(cfg.materials):
        raise ValueError(f"body holds material {int(g.max())} but sim_config defines materials 1..{len(cfg.materials)}")
    data = _layers(g, lambda row: "".join(chr(48 + int(v)) for v in row))
    phase = _layers(phases[g], lambda row: ", ".join(f"{v:g}" for v in row))
    out = [
        "<VXD>",
        '  <Structure replace="VXA.VXC.Structure" Compression="ASCII_READABLE">',
        f"    <X_Voxels>{g.shape[0]}</X_Voxels>",
        f"    <Y_Voxels>{g.shape[1]}</Y_Voxels>",
        f"    <Z_Voxels>{g.shape[2]}</Z_Voxels>",
        "    <Data>",
        *[f"      <Layer><![CDATA[{s}]]></Layer>" for s in data],
        "    </Data>",
        "    <PhaseOffset>",
        *[f"      <Layer><![CDATA[{s}]]></Layer>" for s in phase],
        "    </PhaseOffset>",
        "  </Structure>",
        "</VXD>",
    ]
    return "\n".join(out) + "\n"


def write_vxd(path: str | Path, body: torch.Tensor | np.ndarray, sim_config: SimConfig | None = None,
              crop: bool = True) -> Path:
    """Write ``body`` as a VXD file (see :func:`vxd_string`); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(vxd_string(body, sim_config, crop), encoding="ascii")
    return path


def _parse_structure(structure: ET.Element) -> np.ndarray:
    def count(tag: str) -> int:
        node = structure.find(tag)
        if node is None or not (node.text or "").strip().isdigit():
            raise ValueError(f"VXD/VXA structure lacks a valid <{tag}>")
        return int(node.text)  # type: ignore[arg-type]

    x, y, z = count("X_Voxels"), count("Y_Voxels"), count("Z_Voxels")
    compression = structure.get("Compression", "ASCII_READABLE")
    if compression != "ASCII_READABLE":
        raise ValueError(f"structure Compression must be ASCII_READABLE, got {compression!r}")
    layers = structure.findall("Data/Layer")
    if len(layers) != z:
        raise ValueError(f"structure has {len(layers)} <Layer>s, expected Z_Voxels = {z}")
    grid = np.zeros((x, y, z), dtype=np.uint8)
    for k, layer in enumerate(layers):
        text = (layer.text or "").strip()
        if len(text) != x * y:
            raise ValueError(f"layer {k} holds {len(text)} cells, expected X_Voxels·Y_Voxels = {x * y}")
        codes = np.frombuffer(text.encode("ascii"), dtype=np.uint8).astype(np.int64) - 48
        if codes.min() < 0:
            raise ValueError(f"layer {k} holds characters below '0'")
        grid[:, :, k] = codes.reshape(y, x).T
    return grid


def read_vxd(path: str | Path) -> np.ndarray:
    """The body of a VXD (or a VXA's own structure): uint8 ``[X, Y, Z]``."""
    root = ET.parse(path).getroot()
    structure = root.find("Structure") if root.tag == "VXD" else root.find("VXC/Structure")
    if structure is None:
        raise ValueError(f"{path} has no <Structure> (expected a VXD, or a VXA with VXC/Structure)")
    return _parse_structure(structure)


def vxa_string(sim_config: SimConfig | None = None, colors: tuple[RGB, ...] = PAPER_COLORS,
               record_step_size: int = 100) -> str:
    """The VXA text of ``sim_config`` (default: the paper's locomotion settings) for voxcraft-sim/-viz.

    The structure inside is a 1-voxel placeholder that a VXD replaces. Settings voxcraft cannot express (a fixed dt,
    freeform's ``semantics``/``reward`` switches) are recorded in a comment.
    """
    cfg = sim_config if sim_config is not None else _default_sim_config()
    palette = []
    for i, m in enumerate(cfg.materials, start=1):
        r, g, b = material_rgb(i, colors)
        palette.append(
            f'      <Material ID="{i}">\n'
            f"        <Name>{_material_name(i)}</Name>\n"
            f"        <Display><Red>{r:g}</Red><Green>{g:g}</Green><Blue>{b:g}</Blue><Alpha>1</Alpha></Display>\n"
            "        <Mechanical>\n"
            "          <MatModel>0</MatModel>\n"
            f"          <Elastic_Mod>{m.E:g}</Elastic_Mod>\n"
            "          <Fail_Stress>0</Fail_Stress>\n"
            f"          <Density>{m.density:g}</Density>\n"
            f"          <Poissons_Ratio>{m.poisson:g}</Poissons_Ratio>\n"
            f"          <CTE>{m.cte:g}</CTE>\n"
            f"          <MaterialTempPhase>{m.phase:g}</MaterialTempPhase>\n"
            f"          <uStatic>{m.mu_static:g}</uStatic>\n"
            f"          <uDynamic>{m.mu_kinetic:g}</uDynamic>\n"
            "        </Mechanical>\n"
            "      </Material>"
        )
    stop = cfg.burn_in + cfg.duration
    gravity = cfg.gravity if cfg.gravity != 0 else 0.0
    note = (f"freeform settings: voxel_size={cfg.voxel_size:g} dt={cfg.dt} dt_frac={cfg.dt_frac:g} "
            f"burn_in={cfg.burn_in:g} duration={cfg.duration:g} reward={cfg.reward} semantics={cfg.semantics} "
            f"precision={cfg.precision}; voxcraft has no fixed dt (DtFrac only) and no self-collision here")
    return f"""<?xml version="1.0" encoding="ISO-8859-1"?>
<!-- {note} -->
<VXA Version="1.1">
  <GPU><HeapSize>0.5</HeapSize></GPU>
  <Simulator>
    <EnableCilia>0</EnableCilia>
    <EnableSignals>0</EnableSignals>
    <EnableExpansion>1</EnableExpansion>
    <Integration><DtFrac>{cfg.dt_frac:g}</DtFrac></Integration>
    <Damping>
      <BondDampingZ>{cfg.bond_damping:g}</BondDampingZ>
      <ColDampingZ>{cfg.collision_damping:g}</ColDampingZ>
      <SlowDampingZ>{cfg.global_damping:g}</SlowDampingZ>
    </Damping>
    <AttachDetach><EnableCollision>0</EnableCollision></AttachDetach>
    <Features><VolumeEffectsEnabled>1</VolumeEffectsEnabled></Features>
    <StopCondition>
      <StopConditionFormula><mtSUB><mtVAR>t</mtVAR><mtCONST>{stop:g}</mtCONST></mtSUB></StopConditionFormula>
    </StopCondition>
    <RecordHistory>
      <RecordStepSize>{record_step_size}</RecordStepSize>
      <RecordVoxel>1</RecordVoxel>
      <RecordLink>0</RecordLink>
      <RecordFixedVoxels>0</RecordFixedVoxels>
    </RecordHistory>
  </Simulator>
  <Environment>
    <Thermal>
      <TempEnabled>1</TempEnabled>
      <TempAmplitude>{cfg.temp_amplitude:g}</TempAmplitude>
      <TempBase>25</TempBase>
      <VaryTempEnabled>1</VaryTempEnabled>
      <TempPeriod>{cfg.temp_period:g}</TempPeriod>
    </Thermal>
    <Gravity>
      <GravEnabled>{int(gravity != 0)}</GravEnabled>
      <GravAcc>{gravity:g}</GravAcc>
      <FloorEnabled>{int(cfg.floor)}</FloorEnabled>
    </Gravity>
  </Environment>
  <VXC Version="0.94">
    <Lattice><Lattice_Dim>{cfg.voxel_size:g}</Lattice_Dim></Lattice>
    <Palette>
{chr(10).join(palette)}
    </Palette>
    <Structure Compression="ASCII_READABLE">
      <X_Voxels>1</X_Voxels>
      <Y_Voxels>1</Y_Voxels>
      <Z_Voxels>1</Z_Voxels>
      <Data><Layer><![CDATA[1]]></Layer></Data>
    </Structure>
  </VXC>
</VXA>
"""


def write_vxa(path: str | Path, sim_config: SimConfig | None = None, colors: tuple[RGB, ...] = PAPER_COLORS) -> Path:
    """Write the VXA of ``sim_config`` (see :func:`vxa_string`); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(vxa_string(sim_config, colors), encoding="iso-8859-1")
    return path


# ------------------------------------------------------------------------------------------------ .history


def _quat_to_angle_axis(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quaternions ``[..., 4]`` (w, x, y, z) → rotation angle in degrees ``[...]`` (0..180) and unit axis
    ``[..., 3]`` ((1, 0, 0) for the identity)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    q = np.where(q[..., :1] < 0, -q, q)  # q and −q are the same rotation; w >= 0 keeps the angle in [0, 180]
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = np.degrees(2.0 * np.arctan2(s, q[..., 0]))
    axis = np.where(s[..., None] > 1e-12, v / np.maximum(s[..., None], 1e-12), np.array([1.0, 0.0, 0.0]))
    return angle, axis


def history_string(recording: Recording, robot: int = 0, colors: tuple[RGB, ...] = PAPER_COLORS,
                   rescale: float = 0.001, decimals: int = 4) -> str:
    """The voxcraft ``.history`` text of robot ``robot`` of a recording (format in the module docstring).

    ``rescale``: positions are written in units of ``rescale`` metres (voxcraft's own files use 0.001, i.e. mm);
    ``decimals``: digits after the point of positions and angles. Step numbers are frame indices.
    """
    check_recording(recording, robot)
    if not rescale > 0:
        raise ValueError(f"rescale must be > 0, got {rescale}")
    pos = np.asarray(recording.positions[robot], dtype=np.float64) / rescale  # [F, n, 3]
    angle, axis = _quat_to_angle_axis(recording.orientations[robot])
    mats = np.asarray(recording.materials[robot]).astype(np.int64)
    if mats.size and mats.max() >= 10:
        raise ValueError(f"voxcraft-viz colours materials 0..9 only; robot holds material {int(mats.max())}")
    half = float(recording.voxel_size) / 2.0 / rescale
    lines = [f"{{{{{{setting}}}}}}<rescale>{rescale:g}</rescale>"]
    for m in sorted({int(v) for v in mats}):
        r, g, b = material_rgb(m, colors)
        lines.append(f"{{{{{{setting}}}}}}<matcolor><id>{m}</id><r>{r:.2f}</r><g>{g:.2f}</g><b>{b:.2f}</b>"
                     "<a>1.00</a></matcolor>")
    lines.append(f"{{{{{{setting}}}}}}<voxel_size>{float(recording.voxel_size):g}</voxel_size>")
    d = decimals
    corner = f"{-half:.{d}f},{-half:.{d}f},{-half:.{d}f},{half:.{d}f},{half:.{d}f},{half:.{d}f}"
    for f, t in enumerate(np.asarray(recording.times, dtype=np.float64).tolist()):
        voxels = [
            f"{p[0]:.{d}f},{p[1]:.{d}f},{p[2]:.{d}f},{a:.{d}f},{x[0]:.6f},{x[1]:.6f},{x[2]:.6f},{corner},{m},0,;"
            for p, a, x, m in zip(pos[f].tolist(), angle[f].tolist(), axis[f].tolist(), mats.tolist(), strict=True)
        ]
        lines.append(f"<<<Step{f} Time:{t:.6f}>>>" + "".join(voxels) + "<<<>>>")
    return "\n".join(lines) + "\n"


def write_history(path: str | Path, recording: Recording, robot: int = 0, colors: tuple[RGB, ...] = PAPER_COLORS,
                  rescale: float = 0.001) -> Path:
    """Write robot ``robot`` of ``recording`` as a voxcraft-viz ``.history`` file; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(history_string(recording, robot, colors, rescale), encoding="ascii")
    return path


@dataclass
class History:
    """A parsed ``.history``: ``times [F]`` s, ``positions [F, n, 3]`` m, ``orientations [F, n, 4]`` (w, x, y, z,
    w >= 0), ``materials [n]``, ``voxel_size`` m, ``colors`` {material: (r, g, b, a)}."""

    times: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray
    materials: np.ndarray
    voxel_size: float
    colors: dict[int, tuple[float, float, float, float]]


_STEP = re.compile(r"^<<<Step(\d+) Time:([^>]*)>>>(.*)<<<>>>$")


def read_history(path: str | Path) -> History:
    """Parse a voxcraft ``.history`` file (voxel records only; link records and other lines are skipped)."""
    rescale, voxel_size = 1.0, math.nan
    colors: dict[int, tuple[float, float, float, float]] = {}
    times, frames = [], []
    for line in Path(path).read_text(encoding="ascii", errors="replace").splitlines():
        line = line.strip()
        if line.startswith("{{{setting}}}"):
            node = ET.fromstring(line[len("{{{setting}}}"):])
            if node.tag == "rescale":
                rescale = float(node.text or 1.0)
            elif node.tag == "voxel_size":
                voxel_size = float(node.text or "nan")
            elif node.tag == "matcolor":
                colors[int(node.findtext("id", "0"))] = tuple(float(node.findtext(c, "0")) for c in "rgba")  # type: ignore[assignment]
            continue
        match = _STEP.match(line.split("|")[0])
        if match is None:
            continue
        records = [r for r in match.group(3).split(";") if r.count(",") >= 14]
        frames.append(np.array([[float(v) for v in r.split(",")[:15]] for r in records]).reshape(-1, 15))
        times.append(float(match.group(2)))
    if not frames:
        raise ValueError(f"{path} holds no <<<Step ...>>> voxel frames")
    if len({len(f) for f in frames}) != 1:
        raise ValueError(f"{path}: frames hold different voxel counts {sorted({len(f) for f in frames})}")
    data = np.stack(frames)  # [F, n, 15]
    angle = np.radians(data[..., 3])
    axis = data[..., 4:7]
    axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
    quat = np.concatenate([np.cos(angle / 2)[..., None], np.sin(angle / 2)[..., None] * axis], axis=-1)
    return History(times=np.asarray(times), positions=data[..., 0:3] * rescale, orientations=quat,
                   materials=data[0, :, 13].astype(np.int64), voxel_size=voxel_size, colors=colors)


# ------------------------------------------------------------------------------------------------ meshes


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
    next_id = len(points)

    # Edges used by four faces: pair the faces by voxel and split the second voxel's pair off at a midpoint.
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
    mtl.write_text("".join(f"newmtl {_material_name(m)}\nKd {kd[m]}\nKa 0 0 0\nd 1\n\n" for m in used),
                   encoding="ascii")
    lines = [f"# freeform voxel body: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles",
             f"mtllib {mtl.name}", "o body"]
    lines += [f"v {x:.6g} {y:.6g} {z:.6g}" for x, y, z in mesh.vertices.tolist()]
    for m in used:
        lines.append(f"usemtl {_material_name(m)}")
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


# ------------------------------------------------------------------------------------------------ dispatch

BODY_FORMATS = (".vxd", ".obj", ".stl", ".vox")


def export_body(path: str | Path, body: torch.Tensor | np.ndarray, sim_config: SimConfig | None = None,
                voxel_size: float | None = None) -> Path:
    """Write ``body`` in the format named by ``path``'s suffix (one of :data:`BODY_FORMATS`). ``voxel_size``
    (mesh units) defaults to ``sim_config.voxel_size`` (metres); a VXD is written cropped, a mesh or ``.vox``
    as the cropped body too, so every file starts at the origin."""
    suffix = Path(path).suffix.lower()
    if suffix not in BODY_FORMATS:
        raise ValueError(f"path must end in one of {BODY_FORMATS}, got {Path(path).name!r}")
    g = _crop(as_grid(body, "body", 3))
    if suffix == ".vxd":
        return write_vxd(path, g, sim_config, crop=False)
    if suffix == ".vox":
        return write_vox(path, g)
    size = voxel_size if voxel_size is not None else (sim_config.voxel_size if sim_config is not None else 0.01)
    return write_obj(path, g, size) if suffix == ".obj" else write_stl(path, g, size)


__all__ = [
    "BODY_FORMATS",
    "History",
    "MATERIAL_NAMES",
    "Mesh",
    "export_body",
    "history_string",
    "read_history",
    "read_stl",
    "read_vox",
    "read_vxd",
    "voxel_mesh",
    "vxa_string",
    "vxd_string",
    "write_history",
    "write_obj",
    "write_stl",
    "write_vox",
    "write_vxa",
    "write_vxd",
]
