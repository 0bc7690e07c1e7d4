"""The engine's state, declared once: every array is a table of named columns, here and nowhere else.

The Engine builds its host and device arrays from these tables and the kernels read them by name
(``get3(vr, VR.POS, v)``), so the physics modules never spell an offset and the memory order (``access.py``) is
decided apart from the math — the role ``ti.root.dense(...).place(...)`` plays for Taichi fields. Nothing here
imports Taichi.

A table holds one dtype and is sized by one kind of item:

| table | dtype | items | what |
|---|---|---|---|
| ``VR`` voxel real | real | voxels | pose, momenta, cached Poisson terms, rest size, snapshots |
| ``VI`` voxel int | i32 | voxels | material, robot, flags, the six link slots |
| ``LR`` link real | real | links | last step's link-frame pose, strain, end forces/moments, ω² |
| ``LI`` link int | i32 | links | end voxels, axis, material pair, flags |
| ``RT`` robot real | f64 | robots | clock (t, dt), actuation phase |
| ``RI`` robot int | i32 | robots | status, step count, voxel/link ranges, events, step cap |
| ``MT`` material | real | materials | ``config.MAT_COLUMNS`` |
| ``LT`` link material | real | material pairs | ``config.LINK_COLUMNS`` |

"real" is the simulation's precision (f32 or f64). Robot clocks stay f64 in both: t accumulates ~85 000 steps.
``GP`` (global parameters) is a plain f64 vector, not a table of items.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from freeform.sim.config import LINK_COLUMNS, MAT_COLUMNS

REAL, F64, I32 = "real", "f64", "i32"
ITEM_KINDS = ("voxels", "links", "robots", "materials", "material_pairs")


class Table:
    """The named columns of one state array.

    ``table.NAME`` is the index of column NAME's first component (a Python int: static in kernels);
    ``table.width`` the number of columns; ``table.span(NAME)`` the slice of its components.
    dtype: REAL | F64 | I32. items: which of ITEM_KINDS sizes it (None: a plain vector of ``width`` values).
    """

    def __init__(self, name: str, dtype: str, items: str | None, columns: Sequence[tuple[str, int]]):
        if dtype not in (REAL, F64, I32) or (items is not None and items not in ITEM_KINDS):
            raise ValueError(f"table {name}: bad dtype {dtype!r} or items {items!r}")
        self.name, self.dtype, self.items = name, dtype, items
        self.columns: dict[str, int] = {}
        at = 0
        for col, width in columns:
            if col in self.columns or hasattr(self, col):
                raise ValueError(f"table {name}: column {col!r} declared twice or shadows an attribute")
            self.columns[col] = width
            setattr(self, col, at)
            at += width
        self.width = at

    def span(self, col: str) -> slice:
        """The rows of column ``col`` in a ``[width, items]`` host array."""
        start = getattr(self, col)
        return slice(start, start + self.columns[col])

    def np_dtype(self, precision: str) -> np.dtype:
        """numpy dtype of this table at ``precision`` ("f32" | "f64")."""
        if self.dtype == I32:
            return np.dtype(np.int32)
        if self.dtype == F64 or precision == "f64":
            return np.dtype(np.float64)
        return np.dtype(np.float32)

    def zeros(self, items: int, precision: str) -> np.ndarray:
        """A host array ``[width, items]`` of zeros in this table's dtype."""
        return np.zeros((self.width, items), dtype=self.np_dtype(precision))

    def __repr__(self) -> str:
        return f"Table({self.name}, {self.dtype}, {self.items}, {self.columns})"


# Voxel: position, linear momentum, orientation (w, x, y, z), angular momentum, original position (where a fixed
# voxel is held); transverse area and strain sum for a link along each axis (from the voxel's Poisson strains,
# cached for the next link update); rest size L·(1 + T·CTE) at the temperature in effect, constant temperature;
# positions at the evaluation start/end, last centre-of-mass sample, and that sample at the start/end; the
# actuation command (Switches.command: T = TBASE + A·CMD in place of the clock's sine, or added to it) and the one
# before it, which CMD replaces over the robot's RT.RAMP seconds.
VR = Table("voxel_real", REAL, "voxels", (
    ("POS", 3), ("MOM", 3), ("ORI", 4), ("AMOM", 3), ("POS0", 3), ("TAREA", 3), ("TSUM", 3), ("SIZE", 1),
    ("TBASE", 1), ("PSTART", 3), ("PEND", 3), ("PSAMP", 3), ("PCS", 3), ("PCE", 3), ("CMD", 1), ("CMD0", 1)))
# SLOT: the link in each direction (X_POS, X_NEG, Y_POS, Y_NEG, Z_POS, Z_NEG), -1 = none
VI = Table("voxel_int", I32, "voxels", (("MAT", 1), ("ROBOT", 1), ("FLAGS", 1), ("SLOT", 6)))
# Link: pos2 / angle1v / angle2v of the last step (VX's *_old, for the damping rates), axial strain, force and
# moment on each end in that voxel's frame, and ω² = k_axial/min(m) at the last dt refresh (rl4design's dynamic
# dt: the robot phase takes the max over its links, so no float atomic is needed).
LR = Table("link_real", REAL, "links", (
    ("P2", 3), ("A1", 3), ("A2", 3), ("STRAIN", 1), ("FN", 3), ("FP", 3), ("MN", 3), ("MP", 3), ("OMEGA2", 1)))
# LMAT: the material pair, a column of LT (negative voxel's material · (n_mat + 1) + positive voxel's)
LI = Table("link_int", I32, "links", (("NEG", 1), ("POS", 1), ("AXIS", 1), ("LMAT", 1), ("FLAGS", 1)))
# SIN/COS: sin and cos of 2π·τ/period for the temperature the voxels write this step (τ = the time it is for), so
# each voxel evaluates T = T_base + A·(sin·cos φ + cos·sin φ) without a transcendental call of its own.
# UNTIL: a robot steps only while T < UNTIL (Engine.advance_time: each robot runs until its own clock passes the
# next control time; NO_LIMIT otherwise). RAMP: how long a new command takes to replace the one before (s, 0: at
# once; the ramp ends at UNTIL, Engine.set_commands).
RT = Table("robot_real", F64, "robots", (("T", 1), ("DT", 1), ("DTPREV", 1), ("SIN", 1), ("COS", 1), ("UNTIL", 1),
                                          ("RAMP", 1)))
NO_LIMIT = 1e300  # (finite: fast-math assumes no infinities)
# EVENTS: what the coming step's voxel update snapshots (EV_* bits), decided once per robot per step.
# MAXSTEP: the step at which a robot still running is stopped as STALLED (SimConfig.step_cap).
RI = Table("robot_int", I32, "robots", (
    ("STATUS", 1), ("STEP", 1), ("VSTART", 1), ("VEND", 1), ("LSTART", 1), ("LEND", 1), ("PERIOD", 1),
    ("EVENTS", 1), ("MAXSTEP", 1)))
MT = Table("material", REAL, "materials", tuple((c, 1) for c in MAT_COLUMNS))
LT = Table("link_material", REAL, "material_pairs", tuple((c, 1) for c in LINK_COLUMNS))
# the state tables by the names the kernels read them under (``s.vr``, ``s.ri``, ...: ``access.State``)
TABLES = {"vr": VR, "vi": VI, "lr": LR, "li": LI, "rt": RT, "ri": RI, "mt": MT, "lt": LT}

# A trace sample of one robot (summaries.py; f64, frames of ``[SUMMARY.width, robots]``): its clock and status,
# Σ m·x and Σ m over its voxels, the voxels' lowest and highest coordinates, how many voxels touched the ground,
# Σ q over the voxel orientations (each taken with w ≥ 0)
SUMMARY = Table("robot_summary", F64, "robots", (
    ("T", 1), ("STATUS", 1), ("MX", 3), ("M", 1), ("LO", 3), ("HI", 3), ("CONTACTS", 1), ("Q", 4)))

# What a controller senses of one voxel (sensing.py; f64 rows of the sensing array, after which come the robots'
# rows, ROBOT_SENSE): its position relative to its robot's centre of mass (m), its velocity (m/s), the
# mean |axial strain| of its links, ground contact (0/1)
SENSE = Table("voxel_sense", F64, "voxels", (("REL", 3), ("VEL", 3), ("STRAIN", 1), ("CONTACT", 1)))
# ... and of one robot (the rows after the voxels'): its centre of mass (m), its clock and dt (RT.T, RT.DT) and
# status, so that one copy back tells the host where every robot is after a control step
ROBOT_SENSE = Table("robot_sense", F64, "robots", (("COM", 3), ("T", 1), ("DT", 1), ("STATUS", 1)))

# global parameters (a plain f64 vector)
# TER_*: the terrain's height field S(x, y) = BASE + GX·x + GY·y + grid (terrain.HeightField; the grid itself is the
# real-typed vector ``hf``, NX·NY values, row-major)
GP = Table("params", F64, None, (("BURN_IN", 1), ("T_END", 1), ("GRAVITY", 1), ("TEMP_AMP", 1),
                                     ("TEMP_PERIOD", 1), ("DT_FRAC", 1), ("MAX_STRAIN", 1), ("TER_BASE", 1),
                                     ("TER_GX", 1), ("TER_GY", 1), ("TER_X0", 1), ("TER_Y0", 1), ("TER_CELL", 1),
                                     ("TER_NX", 1), ("TER_NY", 1)))

# The kernels take three buffers, one per element type, each holding several regions (packing.py says where):
# a launch marshals 3 arrays and a step count instead of 11 arrays and 5 counts (the host cost of a launch grows
# with its array arguments: docs/physics.md). Each region is a table (items in memory order), "gp" (GP, one item),
# "hf" (the terrain's height grid, one column of cells), "tr" (the trace, frames × SUMMARY.width rows of robots)
# or "hdr" (HDR, at the start of "ints": where every region starts, and the batch's counts).
BUFFERS = {"reals": ("vr", "lr", "mt", "lt", "hf"), "ints": ("hdr", "vi", "li", "ri"), "f64s": ("rt", "gp", "tr")}
REGIONS = tuple(name for names in BUFFERS.values() for name in names)
# HDR: each region's first element (*_AT) and item stride (*_STRIDE: its capacity in items), the batch's counts,
# the trace's interval in steps (0: off) and frames, and the robots schedule's work counter.
HDR = Table("header", I32, None, (
    *((f"{name.upper()}_{what}", 1) for name in REGIONS for what in ("AT", "STRIDE")),
    ("N_VOXELS", 1), ("N_LINKS", 1), ("N_ROBOTS", 1), ("TRACE_STEPS", 1), ("TRACE_FRAMES", 1), ("QUEUE", 1)))

# voxel flags: STATIC = in static friction; CONTACT = touched the ground at the start of its last step (traces)
STATIC, FIXED, CONTACT = 1, 2, 4
# link flags
SMALL, VALID = 1, 2
# robot status: STALLED = stopped at its step cap (its dt collapsed under rl4design's dynamic step)
RUNNING, DONE, DIVERGED, STALLED = 0, 1, 2, 3
# robot step events: take a COM sample; the step crosses the evaluation start; it crosses the evaluation end
EV_SAMPLE, EV_START, EV_END = 1, 2, 4


class Switches(NamedTuple):
    """The kernels' compile-time switches, in one order everywhere (each combination used compiles once; the
    ``ti.func``s read them through ``ti.static``)."""

    floor: int
    """1: contact with the ground on (``SimConfig.floor``)."""
    terrain: int
    """``terrain.FLAT`` (Voxelyze's own floor code) | ``SMOOTH`` | ``COLUMNS``: how the ground is read."""
    rl4design: int
    """1: the paper simulator's semantics (``SimConfig.semantics="rl4design"``), 0: Voxelyze's."""
    dynamic_dt: int
    """1: rl4design's per-robot dt refresh from the links' ω² (rl4design with ``dt=None``)."""
    command: int = 0
    """1: each voxel's temperature is T_base + A·``VR.CMD`` (``SimConfig.actuation="command"``); 2: T_base +
    A·clip(sine + ``VR.CMD``, −1, 1) (``"residual"``); 0: the sine."""
