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
  oriented outwards), ready for a slicer or Blender (``freeform.mesh``, re-exported here). See :func:`voxel_mesh`
  for the one subtle case.
- **``.vox``** (MagicaVoxel 150): ``VOX `` chunks ``MAIN`` > ``SIZE``, ``XYZI``, ``RGBA``; colour index = material.

Grids are uint8 ``[X, Y, Z]`` material indices (0 = empty), z up, as everywhere in freeform.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from freeform.body import crop as crop_to_bounding_box
from freeform.mesh import Mesh, read_stl, read_vox, voxel_mesh, write_obj, write_stl, write_vox
from freeform.surface import (
    MATERIAL_NAMES,
    PAPER_COLORS,
    RGB,
    as_grid,
    check_recording,
    material_name,
    material_rgb,
)

if TYPE_CHECKING:
    from freeform.sim import Recording, SimConfig

def _default_sim_config() -> SimConfig:
    from freeform.sim import SimConfig

    return SimConfig()


def _crop(grid: np.ndarray) -> np.ndarray:
    """The grid cut to its bounding box (``freeform.body.crop``), so the lowest layer touches the floor as the
    simulator places a body; an empty body is an error here, since the file would hold nothing."""
    if not grid.any():
        raise ValueError("body is empty: nothing to export")
    return crop_to_bounding_box(torch.from_numpy(np.ascontiguousarray(grid))).numpy()


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
    gravity = cfg.gravity if cfg.gravity != 0 else 0.0
    note = (f"freeform settings: voxel_size={cfg.voxel_size:g} dt={cfg.dt} dt_frac={cfg.dt_frac:g} "
            f"burn_in={cfg.burn_in:g} duration={cfg.duration:g} reward={cfg.reward} semantics={cfg.semantics} "
            f"precision={cfg.precision}; voxcraft has no fixed dt (DtFrac only) and no self-collision here")
    return f"""<?xml version="1.0" encoding="ISO-8859-1"?>
<!-- {note} -->
<VXA Version="1.1">
  <GPU><HeapSize>0.5</HeapSize></GPU>
{_simulator(cfg, record_step_size)}
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
{_palette(cfg, colors)}
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


def _palette(cfg: SimConfig, colors: tuple[RGB, ...]) -> str:
    """The VXA's ``<Material>`` entries of ``cfg``'s materials, in ``colors``."""
    palette = []
    for i, m in enumerate(cfg.materials, start=1):
        r, g, b = material_rgb(i, colors)
        palette.append(
            f'      <Material ID="{i}">\n'
            f"        <Name>{material_name(i)}</Name>\n"
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
    return "\n".join(palette)


def _simulator(cfg: SimConfig, record_step_size: int) -> str:
    """The VXA's ``<Simulator>`` section: integration, damping, the stop time and what the history records."""
    stop = cfg.burn_in + cfg.duration
    return f"""  <Simulator>
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
  </Simulator>"""


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
