"""Materials and simulation settings (spec `physics.md` sections 0, 2, 3.2 and 10), plus the derived constants.

Everything numeric lives here as a dataclass field with the spec's default, so the Taichi kernels see only
tables built from these fields. The defaults are the paper's locomotion task: three materials (passive
tissue, muscle A at phase 0, muscle B at phase 0.5 cycles), 5 s burn-in then 5 s of evaluation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from freeform.sim.runtime import BACKENDS
from freeform.sim.terrain import Terrain
from freeform.validation import require

REWARDS = ("max_voxel", "com")
SEMANTICS = ("voxelyze", "rl4design")
ACTUATIONS = ("sine", "command", "residual")
PRECISIONS = ("f32", "f64")
# how the steps are run (``Engine``): "auto" (the CPU's "robots", CUDA's choice), "robots", "flat", "native"
SCHEDULES = ("auto", "robots", "flat", "native")
# the least step cap accepted: a fixed-dt robot needs floor(T/dt) + 1 steps, and the clock's rounding may add one
MIN_STEP_CAP = 1.5
# the fields that say how the steps run, not what is simulated (SimConfig's docstring: "Not physics")
HOW_IT_RUNS = ("chunk_steps", "graph_launches", "backend", "schedule")


@dataclass
class Material:
    """One voxel material (Voxelyze `CVX_Material`, linear model).

    E: Young's modulus (Pa). density: kg/m^3. poisson: Poisson ratio ν (volume effects; 0 switches them off).
    mu_static / mu_kinetic: floor friction coefficients. cte: coefficient of thermal expansion (1/degree),
    which makes a voxel a muscle. phase: actuation phase offset in cycles (VXD `PhaseOffset`).
    """

    E: float = 1e5
    density: float = 1500.0
    poisson: float = 0.35
    mu_static: float = 1.0
    mu_kinetic: float = 0.5
    cte: float = 0.0
    phase: float = 0.0


def _paper_materials() -> list[Material]:
    return [Material(), Material(cte=0.01, phase=0.0), Material(cte=0.01, phase=0.5)]


@dataclass
class SimConfig:
    """Settings of one simulation batch; every number of the spec's parameter table is a field.

    voxel_size: lattice dimension L (m). materials[i] is the material of index i + 1 (0 = empty).
    bond_damping / global_damping / collision_damping: damping ratios ζ (internal, global, floor).
    gravity: vertical acceleration (m/s^2, negative = down; 0 switches gravity off).
    temp_amplitude / temp_period: actuation T(t) = A·sin(2π(t/period + phase)) (degrees, s).
    actuation: "sine" (open loop: each voxel's temperature follows the robot's clock and its material's phase) or
        "command" (closed loop: T = T_base + A·c with c each voxel's command, written by a controller between
        calls: ``Engine.set_commands``; c in [−1, 1] spans the sine's range; the clock still runs) or "residual"
        (the sine corrected: T = T_base + A·clip(sin(2π(t/period + phase)) + c, −1, 1), the sine computed every step
        as open loop; zero commands are the open-loop gait, bit for bit).
    dt: fixed time step (s); None = dt_frac × the recommended step of each robot (spec section 10).
    burn_in / duration: evaluation window (s) that the reward measures.
    reward: deprecated — which displacement ``SimResult.displacement`` repeats; the result carries both
        (``max_voxel_displacement``, ``com_displacement``) and the task chooses (``LocomotionTask(measure=...)``,
        ``task.options.measure``). ``sim.reward=com`` still selects the centre of mass there, with a warning.
    semantics: "voxelyze" (VX) or "rl4design" (the paper simulator's deviations, spec section 13).
    precision: "f32" (fast; normalised quaternions, atan2 rotation vectors) or "f64" (VX arithmetic).
    floor: floor contact and friction on/off.
    terrain: the ground's shape (``freeform.sim.Terrain``; flat by default, Voxelyze's floor bit for bit).
    max_strain: a link strain above this marks the robot diverged (VX's check; non-finite states too).
    chunk_steps: steps per kernel launch between host-side checks (per-robot schedule).
    graph_launches: the flat schedule's launches (``UNROLL`` steps each) issued as one compute graph from C++
        (Taichi's ``ti.graph``; quadrants has none and launches from Python); 0 = every launch from Python. Not
        physics: the same launches in the same order, the same bits.
    step_cap: a robot still running after ``step_cap`` × the steps its burn_in + duration take at its initial dt
        is stopped and flagged stalled (reward 0): under rl4design's dynamic dt a robot whose step collapses
        would otherwise hold up the whole batch. Healthy robots stay within a few % of their initial dt.
    backend: "taichi" (Taichi 1.7.4) | "quadrants" (its maintained fork, the ``quadrants`` extra) | None (the
        environment's ``FREEFORM_BACKEND``, else taichi). One backend per process: it must be chosen before the
        process's first simulation (``freeform.sim.runtime``). Not physics: both run the same kernels.
    schedule: how the steps run (``freeform.sim.Engine``): "auto" | "robots" | "flat" | "native" (the CPU's step
        compiled by the host's C++ compiler, ≈ 2.2× the robots schedule on 2 cores, for the f32 fast-math path
        with Voxelyze semantics, a fixed dt and the flat floor: docs/physics-native.md, "The native schedule"; "auto"
        takes it on an AVX-512 CPU where it runs the batch). Not physics beyond rounding: native agrees with
        robots as closely as fast-math with the strict path.
    """

    voxel_size: float = 0.01
    materials: list[Material] = field(default_factory=_paper_materials)
    bond_damping: float = 1.0
    global_damping: float = 0.03
    collision_damping: float = 0.8
    gravity: float = -9.81
    temp_amplitude: float = 10.0
    temp_period: float = 0.25
    dt: float | None = None
    dt_frac: float = 0.95
    burn_in: float = 5.0
    duration: float = 5.0
    reward: str = "max_voxel"
    semantics: str = "voxelyze"
    actuation: str = "sine"
    precision: str = "f32"
    floor: bool = True
    terrain: Terrain = field(default_factory=Terrain)
    max_strain: float = 100.0
    chunk_steps: int = 2000
    graph_launches: int = 64
    step_cap: float = 3.0
    backend: str | None = None
    schedule: str = "auto"

    def physics_differences(self, other: SimConfig) -> list[str]:
        """The fields on which ``other`` simulates another physics than this config: every field but
        :data:`HOW_IT_RUNS` (a run of another schedule or backend plays the same robot)."""
        return [k for k in vars(self) if k not in HOW_IT_RUNS and getattr(self, k) != getattr(other, k)]

    def validate(self, key: str = "SimConfig") -> None:
        """Raise ``ValueError`` naming ``<key>.<field>`` for the first value outside its allowed values
        (``key="sim"`` from the command line)."""
        require(self.reward in REWARDS, f"{key}.reward", f"one of {REWARDS}", self.reward)
        require(self.semantics in SEMANTICS, f"{key}.semantics", f"one of {SEMANTICS}", self.semantics)
        require(self.actuation in ACTUATIONS, f"{key}.actuation", f"one of {ACTUATIONS}", self.actuation)
        require(self.precision in PRECISIONS, f"{key}.precision", f"one of {PRECISIONS}", self.precision)
        require(self.voxel_size > 0, f"{key}.voxel_size", "> 0", self.voxel_size)
        require(1 <= len(self.materials) <= 254, f"{key}.materials", "1..254 materials", len(self.materials))
        for i, m in enumerate(self.materials):
            require(m.E > 0, f"{key}.materials[{i}].E", "> 0", m.E)
            require(m.density > 0, f"{key}.materials[{i}].density", "> 0", m.density)
            require(0 <= m.poisson < 0.5, f"{key}.materials[{i}].poisson", "in [0, 0.5)", m.poisson)
        require(self.dt is None or self.dt > 0, f"{key}.dt", "None or > 0", self.dt)
        require(0 < self.dt_frac <= 1, f"{key}.dt_frac", "in (0, 1]", self.dt_frac)
        require(self.burn_in >= 0, f"{key}.burn_in", ">= 0", self.burn_in)
        require(self.duration > 0, f"{key}.duration", "> 0", self.duration)
        require(self.temp_period > 0, f"{key}.temp_period", "> 0", self.temp_period)
        require(self.chunk_steps >= 1, f"{key}.chunk_steps", ">= 1", self.chunk_steps)
        require(isinstance(self.graph_launches, int) and self.graph_launches >= 0, f"{key}.graph_launches",
                "an integer >= 0 (0: every launch from Python)", self.graph_launches)
        # Times the protocol's steps; less could stop healthy robots whose dt dips for a while.
        require(self.step_cap >= MIN_STEP_CAP, f"{key}.step_cap", f">= {MIN_STEP_CAP}", self.step_cap)
        require(self.backend in (None, *BACKENDS), f"{key}.backend", f"None or one of {BACKENDS}", self.backend)
        require(self.schedule in SCHEDULES, f"{key}.schedule", f"one of {SCHEDULES}", self.schedule)
        self.terrain.validate(f"{key}.terrain")
        if self.terrain.kind == "steps" or (self.terrain.kind == "heightmap" and not self.terrain.smooth):
            # a voxel's contact looks at its own cell and the nearest neighbours only
            cell = self.terrain.depth if self.terrain.kind == "steps" else self.terrain.cell_size
            require(cell >= self.voxel_size, f"{key}.terrain.{'depth' if self.terrain.kind == 'steps' else 'cell_size'}",
                    f">= voxel_size ({self.voxel_size}) for columnar terrain", cell)


# Column names of the material tables that the kernels read (one column per material index, 0 = empty).
# MINV/IINV (1/m, 1/I: VX's _massInverse/_momentInertiaInverse), MG (m·g) and DAMP (2·√m·ζ_int, the numerator of
# VX's dampingMultiplier) are folded here so the kernels multiply instead of dividing every step.
MAT_COLUMNS = ("L", "MASS", "INERTIA", "SQRTM", "CG", "CGR", "CC", "KPEN", "MUS", "MUK", "ZINT", "CTE",
               "PHASE", "NU", "E", "SINPHI", "COSPHI", "MINV", "IINV", "MG", "DAMP") + \
    tuple(f"PB{k}" for k in range(1, 9))
# PB1..PB8: binomial coefficients C(−ν, k) of (1+x)^(−ν) − 1 = Σ_k C(−ν, k)·x^k, the f32 kernels' Poisson series
POISSON_SERIES_TERMS = 8
# PSNEG/PSPOS: VX_Link::axialStrain's factor for the link's negative / positive voxel, 2/(1+r) and 2r/(1+r).
LINK_COLUMNS = ("E", "NU", "EHAT", "A1", "A2", "B1", "B2", "B3", "SQA1", "SQA2XIP", "SQB1", "SQB2XFMP",
                "SQB3XIP", "RATIO", "PSNEG", "PSPOS")


def e_hat(E: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """Ê = E/((1−2ν)(1+ν)), the constrained modulus (VX_Material.cpp)."""
    return E / ((1 - 2 * nu) * (1 + nu))


def material_table(cfg: SimConfig) -> np.ndarray:
    """Per-voxel constants of spec section 2: float64 ``[len(MAT_COLUMNS), n_mat + 1]`` (column 0 unused)."""
    L = cfg.voxel_size
    n = len(cfg.materials) + 1
    t = np.zeros((len(MAT_COLUMNS), n))
    col = {c: i for i, c in enumerate(MAT_COLUMNS)}
    for j, m in enumerate(cfg.materials, start=1):
        mass = m.density * L**3
        inertia = mass * L**2 / 6  # solid cube, the same about every axis
        t[col["L"], j] = L
        t[col["MASS"], j] = mass
        t[col["INERTIA"], j] = inertia
        t[col["SQRTM"], j] = math.sqrt(mass)
        t[col["CG"], j] = cfg.global_damping * 2 * math.sqrt(mass * m.E * L)
        t[col["CGR"], j] = cfg.global_damping * 2 * math.sqrt(inertia * m.E * L**3)
        t[col["CC"], j] = cfg.collision_damping * 2 * math.sqrt(mass * m.E * L)
        t[col["KPEN"], j] = 2 * m.E * L  # EA/ℓ of half a voxel
        t[col["MUS"], j] = m.mu_static
        t[col["MUK"], j] = m.mu_kinetic
        t[col["ZINT"], j] = cfg.bond_damping
        t[col["CTE"], j] = m.cte
        t[col["PHASE"], j] = m.phase
        t[col["NU"], j] = m.poisson
        t[col["E"], j] = m.E
        t[col["SINPHI"], j] = math.sin(2 * math.pi * m.phase)
        t[col["COSPHI"], j] = math.cos(2 * math.pi * m.phase)
        t[col["MINV"], j] = 1.0 / mass
        t[col["IINV"], j] = 1.0 / inertia
        t[col["MG"], j] = mass * cfg.gravity
        t[col["DAMP"], j] = 2.0 * math.sqrt(mass) * cfg.bond_damping
        c = 1.0
        for k in range(1, POISSON_SERIES_TERMS + 1):
            c *= (-m.poisson - (k - 1)) / k
            t[col[f"PB{k}"], j] = c
    return t


def link_table(cfg: SimConfig) -> np.ndarray:
    """Beam constants of every material pair (spec section 3.2): float64 ``[len(LINK_COLUMNS), (n_mat+1)²]``.

    Column ``i·(n_mat+1) + j`` is the link whose negative voxel has material i and positive voxel material j.
    """
    n = len(cfg.materials) + 1
    t = np.zeros((len(LINK_COLUMNS), n * n))
    col = {c: i for i, c in enumerate(LINK_COLUMNS)}
    L = cfg.voxel_size  # nominal size: the mean of two equal nominal sizes
    for i, mi in enumerate(cfg.materials, start=1):
        for j, mj in enumerate(cfg.materials, start=1):
            E = 2 * mi.E * mj.E / (mi.E + mj.E)  # springs in series
            eh1, eh2 = e_hat(np.float64(mi.E), np.float64(mi.poisson)), e_hat(np.float64(mj.E), np.float64(mj.poisson))
            eh = 2 * eh1 * eh2 / (eh1 + eh2)
            # ν chosen so that Ê(E, ν) = the series Ê (VX_MaterialLink.cpp); exact ν for equal materials
            if mi.poisson == 0 and mj.poisson == 0:
                nu = 0.0
            else:
                c2 = (eh - E) / (2 * eh) + 1.0 / 16
                nu = math.sqrt(c2) - 0.25
                if mi.poisson == mj.poisson:
                    nu = mi.poisson
            k = i * n + j
            a1, a2 = E * L, E * L**3 / (12 * (1 + nu))
            b1, b2, b3 = E * L, E * L**2 / 2, E * L**3 / 6
            t[col["E"], k] = E
            t[col["NU"], k] = nu
            t[col["EHAT"], k] = e_hat(E, nu) if nu != 0 else E
            t[col["A1"], k], t[col["A2"], k] = a1, a2
            t[col["B1"], k], t[col["B2"], k], t[col["B3"], k] = b1, b2, b3
            t[col["SQA1"], k] = math.sqrt(a1)
            t[col["SQA2XIP"], k] = math.sqrt(a2 * L * L / 6)
            t[col["SQB1"], k] = math.sqrt(b1)
            t[col["SQB2XFMP"], k] = math.sqrt(b2 * L / 2)
            t[col["SQB3XIP"], k] = math.sqrt(b3 * L * L / 6)
            ratio = mj.E / mi.E  # strainRatio = E_pos / E_neg
            t[col["RATIO"], k] = ratio
            t[col["PSNEG"], k] = 2.0 / (1.0 + ratio)
            t[col["PSPOS"], k] = 2.0 * ratio / (1.0 + ratio)
    return t
