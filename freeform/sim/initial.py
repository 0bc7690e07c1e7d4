"""A batch's state before its first step, as host tables: pure numpy, no Taichi (testable on its own).

``initial_state(layout, config)`` fills every table of ``state.py`` by column name — the voxels' poses, rest sizes
and flags, the links' ends and material pairs, the robots' clocks, ranges, step caps and step 0's events, the
material tables — and the global parameters and the terrain's height grid. The ``Engine`` uploads them as they are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from freeform.sim.config import SimConfig, e_hat, link_table, material_table
from freeform.sim.layout import Layout
from freeform.sim.state import (
    EV_END,
    EV_SAMPLE,
    EV_START,
    FIXED,
    GP,
    LI,
    LT,
    MT,
    NO_LIMIT,
    RI,
    RT,
    RUNNING,
    SMALL,
    STATIC,
    TABLES,
    VI,
    VR,
    Switches,
)
from freeform.sim.terrain import FLAT, HeightField, placement

INT32_MAX = np.iinfo(np.int32).max


@dataclass
class InitialState:
    """What :func:`initial_state` returns. ``tables``: name -> host table ``[columns, items]`` (``state.TABLES``);
    ``globals``: the ``GP`` vector (f64); ``height_grid``: the terrain's grid (flattened; one value on flat
    ground); ``dt0``/``max_steps``: each robot's first step (s) and step cap ``[R]``; ``offset``: each robot's
    placement on the terrain ``[R, 3]`` (m); ``counts``: items per kind (``state.ITEM_KINDS``)."""

    tables: dict[str, np.ndarray]
    globals: np.ndarray
    height_grid: np.ndarray
    terrain: HeightField
    switches: Switches
    counts: dict[str, int]
    dt0: np.ndarray
    max_steps: np.ndarray
    offset: np.ndarray


def recommended_dt(layout: Layout, cfg: SimConfig) -> np.ndarray:
    """Voxelyze's recommendedTimeStep per robot at rest (spec section 10): float64 ``[R]``.

    1/(2π·sqrt(max over links of k_ax/min(m₁, m₂))) with k_ax = E·L (ν = 0) or Ê·A/L0 (ν ≠ 0, at zero strain);
    a robot without links uses E·L/m of its voxels.
    """
    mt = material_table(cfg)
    n_mat = len(cfg.materials) + 1
    L = cfg.voxel_size
    E = np.array([0.0] + [m.E for m in cfg.materials])
    mass = mt[MT.MASS]
    omega2 = np.zeros(layout.num_robots)
    # voxels alone: E·L/m (VX uses this when there are no links)
    np.maximum.at(omega2, layout.voxel_robot, E[layout.material] * L / mass[layout.material])
    if layout.num_links:
        lt = link_table(cfg)
        mn, mp = layout.material[layout.link_neg], layout.material[layout.link_pos]
        k = mn * n_mat + mp
        nul, El = lt[LT.NU, k], lt[LT.E, k]
        kax = np.where(nul == 0, El * L, e_hat(El, nul) * L * L / L)
        per_link = kax / np.minimum(mass[mn], mass[mp])
        has_links = np.zeros(layout.num_robots, dtype=bool)
        has_links[layout.link_robot] = True
        link_omega = np.zeros(layout.num_robots)
        np.maximum.at(link_omega, layout.link_robot, per_link)
        omega2 = np.where(has_links, link_omega, omega2)
    return 1.0 / (2 * math.pi * np.sqrt(omega2))


def initial_state(layout: Layout, config: SimConfig) -> InitialState:
    """The batch ``layout`` at t = 0 under ``config`` (module docstring)."""
    rl4design = config.semantics == "rl4design"
    n_mat = len(config.materials) + 1
    counts = {"voxels": layout.num_voxels, "links": layout.num_links, "robots": layout.num_robots,
              "materials": n_mat, "material_pairs": n_mat**2}
    dt0 = np.full(layout.num_robots, float(config.dt)) if config.dt is not None else (
        config.dt_frac * recommended_dt(layout, config))
    t_end = config.burn_in + config.duration
    # the step cap: step_cap × the protocol's steps at the initial dt (+1: the first step past t_end)
    max_steps = np.minimum(np.ceil(config.step_cap * t_end / dt0) + 1, INT32_MAX).astype(np.int64)
    # the terrain: each robot rests on it under its footprint (flat ground: no offset at all)
    L = config.voxel_size
    terrain = config.terrain.field(L)
    offset = placement(config.terrain, terrain, layout.lattice, layout.voxel_robot, layout.num_robots, L)
    # rl4design refreshes dt every few steps unless dt is fixed
    switches = Switches(floor=int(config.floor), terrain=int(terrain.mode), rl4design=int(rl4design),
                        dynamic_dt=int(rl4design and config.dt is None),
                        command={"sine": 0, "command": 1, "residual": 2}[config.actuation])
    precision = config.precision
    tables = {name: t.zeros(counts[t.items], precision) for name, t in TABLES.items()}
    _voxels(tables["vr"], tables["vi"], layout, config, terrain, offset)
    _links(tables["li"], layout, n_mat)
    _robots(tables["rt"], tables["ri"], layout, config, dt0, max_steps)
    real = np.float64 if precision == "f64" else np.float32
    tables["mt"] = material_table(config).astype(real)
    tables["lt"] = link_table(config).astype(real)
    gp, grid = _globals(config, terrain)
    return InitialState(tables=tables, globals=gp, height_grid=grid, terrain=terrain, switches=switches,
                        counts=counts, dt0=dt0, max_steps=max_steps, offset=offset)


def _voxels(vr: np.ndarray, vi: np.ndarray, layout: Layout, config: SimConfig, terrain: HeightField,
            offset: np.ndarray) -> None:
    """Poses (resting on the terrain), momenta, rest sizes at the first temperature, flags, link slots."""
    rl4design = config.semantics == "rl4design"
    mt = material_table(config)
    pos = layout.lattice.astype(np.float64) * config.voxel_size
    if terrain.mode != FLAT and layout.num_voxels:
        pos = pos + offset[layout.voxel_robot]
    mass = mt[MT.MASS][layout.material]
    for c in ("POS", "POS0", "PSTART", "PEND", "PSAMP", "PCS", "PCE"):
        vr[VR.span(c)] = pos.T
    vr[VR.span("MOM")] = (layout.velocity * mass[:, None]).T
    vr[VR.ORI] = 1.0
    vr[VR.TBASE] = layout.temp_base
    if rl4design or config.actuation == "command":
        temp = layout.temp_base  # rl4design starts at T = 0 (plus any constant offset); commands start at 0
    else:
        phase = np.array([0.0] + [mm.phase for mm in config.materials])[layout.material]
        temp = layout.temp_base + config.temp_amplitude * np.sin(2 * math.pi * phase)
    # rest size L·(1 + T·CTE) in the kernels' precision and order of operations (voxels.base_size)
    real = np.float64 if config.precision == "f64" else np.float32
    L_v = mt[MT.L][layout.material].astype(real)
    vr[VR.SIZE] = L_v * (real(1.0) + temp.astype(real) * mt[MT.CTE][layout.material].astype(real))
    # transverse areas before any strain: L² (voxels.transverse); strain sums start at 0
    vr[VR.span("TAREA")] = (L_v * L_v)[None, :]
    vi[VI.MAT] = layout.material
    vi[VI.ROBOT] = layout.voxel_robot
    # VX starts every voxel in static friction; the paper simulator starts none there
    vi[VI.FLAGS] = np.where(layout.fixed, FIXED, 0) | (0 if rl4design else STATIC)
    vi[VI.span("SLOT")] = layout.slots.T


def _links(li: np.ndarray, layout: Layout, n_mat: int) -> None:
    """Each link's end voxels, axis and material pair (negative end's material × n + positive end's)."""
    li[LI.NEG], li[LI.POS], li[LI.AXIS] = layout.link_neg, layout.link_pos, layout.link_axis
    li[LI.LMAT] = layout.material[layout.link_neg] * n_mat + layout.material[layout.link_pos]
    li[LI.FLAGS] = SMALL


def _robots(rt: np.ndarray, ri: np.ndarray, layout: Layout, config: SimConfig, dt0: np.ndarray,
            max_steps: np.ndarray) -> None:
    """Clocks, the actuation phase of step 0, status, voxel and link ranges, sample period, step cap, and step 0's
    snapshot events (``clock.robot_advance`` decides every later step's with the same arithmetic)."""
    rl4design = config.semantics == "rl4design"
    t_end = config.burn_in + config.duration
    rt[RT.DT] = dt0
    rt[RT.UNTIL] = NO_LIMIT
    # actuation phase of the temperature written during step 0: T(dt) for VX, T(0) for rl4design
    tau = np.zeros(layout.num_robots) if rl4design else dt0
    rt[RT.SIN] = np.sin(2 * math.pi * tau / config.temp_period)
    rt[RT.COS] = np.cos(2 * math.pi * tau / config.temp_period)
    ri[RI.STATUS] = RUNNING
    ri[RI.VSTART], ri[RI.VEND] = layout.voxel_start[:-1], layout.voxel_start[1:]
    ri[RI.LSTART], ri[RI.LEND] = layout.link_start[:-1], layout.link_start[1:]
    ri[RI.PERIOD] = np.maximum(1, np.floor(config.temp_period / dt0)).astype(np.int32)
    ri[RI.MAXSTEP] = max_steps
    t_after = 0.0 + dt0
    ri[RI.EVENTS] = (np.where(1 % ri[RI.PERIOD] == 0, EV_SAMPLE, 0)
                     | np.where((0.0 <= config.burn_in) & (t_after > config.burn_in), EV_START, 0)
                     | np.where((0.0 <= t_end) & (t_after > t_end), EV_END, 0))


def _globals(config: SimConfig, terrain: HeightField) -> tuple[np.ndarray, np.ndarray]:
    """The ``GP`` vector (protocol, gravity, actuation, divergence limit, the terrain's parameters) and the
    terrain's height grid."""
    gp = np.zeros(GP.width)
    gp[GP.BURN_IN] = config.burn_in
    gp[GP.T_END] = config.burn_in + config.duration
    gp[GP.GRAVITY] = config.gravity
    gp[GP.TEMP_AMP] = config.temp_amplitude
    gp[GP.TEMP_PERIOD] = config.temp_period
    gp[GP.DT_FRAC] = config.dt_frac
    gp[GP.MAX_STRAIN] = config.max_strain
    params, grid = terrain.arrays()
    for c, value in params.items():
        gp[getattr(GP, c)] = value
    return gp, grid


__all__ = ["InitialState", "initial_state", "recommended_dt"]
