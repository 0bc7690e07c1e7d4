"""The low-level engine: one batch's state in Taichi ndarrays, advanced step by step.

``Simulator`` builds on this; tests and tools use it directly for what the public API does not expose —
fixed voxels, initial velocities and constant temperatures (all on the ``Layout``), per-step traces,
link strains. Nothing here loops over voxels in Python.
"""

from __future__ import annotations

import math

import numpy as np

from freeform.sim import runtime
from freeform.sim.config import SimConfig, e_hat, link_table, material_table
from freeform.sim.kernels import (  # noqa: F401  (re-exported)
    DIVERGED,
    DONE,
    EV_END,
    EV_SAMPLE,
    EV_START,
    FIXED,
    GP,
    LI,
    LR,
    MT,
    NGP,
    NLI,
    NLR,
    NRI,
    NRT,
    NVI,
    NVR,
    RI,
    RT,
    RUNNING,
    SMALL,
    STATIC,
    UNROLL,
    VI,
    VR,
    make_kernels,
)
from freeform.sim.layout import Layout

SCHEDULES = ("auto", "robots", "flat")


def recommended_dt(layout: Layout, cfg: SimConfig) -> np.ndarray:
    """Voxelyze's recommendedTimeStep per robot at rest (spec section 10): float64 ``[R]``.

    1/(2π·sqrt(max over links of k_ax/min(m₁, m₂))) with k_ax = E·L (ν = 0) or Ê·A/L0 (ν ≠ 0, at zero strain);
    a robot without links uses E·L/m of its voxels.
    """
    mt = material_table(cfg)
    n_mat = len(cfg.materials) + 1
    L = cfg.voxel_size
    E = np.array([0.0] + [m.E for m in cfg.materials])
    mass = mt[1]  # MAT_COLUMNS[1] == "MASS"
    omega2 = np.zeros(layout.num_robots)
    # voxels alone: E·L/m (VX uses this when there are no links)
    np.maximum.at(omega2, layout.voxel_robot, E[layout.material] * L / mass[layout.material])
    if layout.num_links:
        lt = link_table(cfg)
        mn, mp = layout.material[layout.link_neg], layout.material[layout.link_pos]
        k = mn * n_mat + mp
        nul, El = lt[1, k], lt[0, k]
        kax = np.where(nul == 0, El * L, e_hat(El, nul) * L * L / L)
        per_link = kax / np.minimum(mass[mn], mass[mp])
        has_links = np.zeros(layout.num_robots, dtype=bool)
        has_links[layout.link_robot] = True
        link_omega = np.zeros(layout.num_robots)
        np.maximum.at(link_omega, layout.link_robot, per_link)
        omega2 = np.where(has_links, link_omega, omega2)
    return 1.0 / (2 * math.pi * np.sqrt(omega2))


class Engine:
    """A batch of robots in Taichi ndarrays. ``advance(n)`` runs n steps of every still-running robot.

    schedule: "robots" (one worker per CPU thread taking whole robots from a queue, many steps per launch;
    the CPU default; arrays in "aos" order) or "flat" (one thread per link/voxel/robot; the CUDA default; "soa").
    Both compute the same physics (bit for bit in f64 up to fast-math reassociation, see docs/physics.md).
    """

    def __init__(self, layout: Layout, config: SimConfig, arch: str = "auto", schedule: str = "auto"):
        config.validate()
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
        self.arch = runtime.ensure(arch)
        self.schedule = ("flat" if self.arch == "cuda" else "robots") if schedule == "auto" else schedule
        self.layout, self.config = layout, config
        # one thread per robot walks its own voxels and links: keep each item's columns together ("aos", one
        # voxel = a few cache lines); one thread per item (GPU): neighbouring threads read neighbouring addresses
        self.order = "aos" if self.schedule == "robots" else "soa"
        self.kernels = make_kernels(config.precision, self.order)
        self.np_real = np.float64 if config.precision == "f64" else np.float32
        self.ifx = int(config.semantics == "rl4design")
        self.dyn = int(self.ifx == 1 and config.dt is None)  # rl4design refreshes dt every 10 steps
        n, m, R = layout.num_voxels, layout.num_links, layout.num_robots
        L = config.voxel_size
        mt = material_table(config)

        if config.dt is not None:
            dt0 = np.full(R, float(config.dt))
        else:
            dt0 = config.dt_frac * recommended_dt(layout, config)
        self.dt0 = dt0

        vr = np.zeros((NVR, n))
        pos = layout.lattice.astype(np.float64) * L
        mass = mt[1][layout.material]
        for c in (VR.POS, VR.POS0, VR.PSTART, VR.PEND, VR.PSAMP, VR.PCS, VR.PCE):
            vr[c:c + 3] = pos.T
        vr[VR.MOM:VR.MOM + 3] = (layout.velocity * mass[:, None]).T
        vr[VR.ORI] = 1.0
        vr[VR.TBASE] = layout.temp_base
        if self.ifx:
            temp = layout.temp_base  # rl4design starts at T = 0 (plus any constant offset)
        else:
            phase = np.array([0.0] + [mm.phase for mm in config.materials])[layout.material]
            temp = layout.temp_base + config.temp_amplitude * np.sin(2 * math.pi * phase)
        # rest size L·(1 + T·CTE) in the kernels' precision and order of operations (kernels.base_size)
        real = self.np_real
        L_v = mt[MT.L][layout.material].astype(real)
        vr[VR.SIZE] = L_v * (real(1.0) + temp.astype(real) * mt[MT.CTE][layout.material].astype(real))
        # transverse areas before any strain: L² (kernels.transverse); strain sums start at 0
        vr[VR.TAREA:VR.TAREA + 3] = (L_v * L_v)[None, :]

        vi = np.zeros((NVI, n), dtype=np.int32)
        vi[VI.MAT] = layout.material
        vi[VI.ROBOT] = layout.voxel_robot
        # VX starts every voxel in static friction; the paper simulator starts none there
        vi[VI.FLAGS] = np.where(layout.fixed, FIXED, 0) | (0 if self.ifx else STATIC)
        vi[VI.SLOT:VI.SLOT + 6] = layout.slots.T

        li = np.zeros((NLI, m), dtype=np.int32)
        li[LI.NEG], li[LI.POS], li[LI.AXIS] = layout.link_neg, layout.link_pos, layout.link_axis
        n_mat = len(config.materials) + 1
        li[LI.LMAT] = layout.material[layout.link_neg] * n_mat + layout.material[layout.link_pos]
        li[LI.FLAGS] = SMALL

        rt = np.zeros((NRT, R))
        rt[RT.DT] = dt0
        # actuation phase of the temperature written during step 0: T(dt) for VX, T(0) for rl4design
        tau = np.zeros(R) if self.ifx else dt0
        rt[RT.SIN] = np.sin(2 * math.pi * tau / config.temp_period)
        rt[RT.COS] = np.cos(2 * math.pi * tau / config.temp_period)
        ri = np.zeros((NRI, R), dtype=np.int32)
        ri[RI.STATUS] = RUNNING
        ri[RI.VSTART], ri[RI.VEND] = layout.voxel_start[:-1], layout.voxel_start[1:]
        ri[RI.LSTART], ri[RI.LEND] = layout.link_start[:-1], layout.link_start[1:]
        ri[RI.PERIOD] = np.maximum(1, np.floor(config.temp_period / dt0)).astype(np.int32)
        # step 0's snapshots (kernels.robot_advance decides them for every later step, with the same arithmetic)
        t_end = config.burn_in + config.duration
        t_after = 0.0 + dt0
        ri[RI.EVENTS] = (np.where(1 % ri[RI.PERIOD] == 0, EV_SAMPLE, 0)
                         | np.where((0.0 <= config.burn_in) & (t_after > config.burn_in), EV_START, 0)
                         | np.where((0.0 <= t_end) & (t_after > t_end), EV_END, 0))

        gp = np.zeros(NGP)
        gp[GP.BURN_IN] = config.burn_in
        gp[GP.T_END] = config.burn_in + config.duration
        gp[GP.GRAVITY] = config.gravity
        gp[GP.TEMP_AMP] = config.temp_amplitude
        gp[GP.TEMP_PERIOD] = config.temp_period
        gp[GP.DT_FRAC] = config.dt_frac
        gp[GP.MAX_STRAIN] = config.max_strain

        # Taichi ndarrays cannot have a zero-length axis: pad empty batches with one inert column
        self.vr = self._upload(_pad(vr.astype(real)))
        self.vi = self._upload(_pad(vi))
        self.lr = self._upload(_pad(np.zeros((NLR, m), dtype=real)))
        self.li = self._upload(_pad(li))
        self.rt = self._upload(rt if R else np.zeros((NRT, 1)))
        self.ri = self._upload(ri if R else np.full((NRI, 1), DONE, dtype=np.int32))
        self.mt = self._upload(mt.astype(real))
        self.lt = self._upload(link_table(config).astype(real))
        self.gp = runtime.from_numpy(gp)
        # robots schedule: a work counter, and one worker per CPU thread (per robot on a GPU)
        self._queue = runtime.from_numpy(np.zeros(1, dtype=np.int32))
        self._workers = max(1, min(R, runtime.num_threads() if self.arch == "cpu" else R))
        self.steps_done = 0

    # ------------------------------------------------------------------ host <-> device, in the kernels' order
    def _upload(self, a: np.ndarray):
        """A Taichi ndarray holding ``a`` (``[columns, items]``) in this engine's memory order."""
        if self.order == "aos":
            return runtime.from_numpy(a.T, rows_as_vectors=True)
        return runtime.from_numpy(a)

    def _download(self, arr) -> np.ndarray:
        """``[columns, items]`` host copy of an array uploaded by ``_upload``."""
        a = runtime.to_numpy(arr)
        return a.T if self.order == "aos" else a

    # ------------------------------------------------------------------ stepping
    def advance(self, n_steps: int) -> None:
        """Run ``n_steps`` steps of every robot still running (finished/diverged robots stay frozen)."""
        if n_steps <= 0 or self.layout.num_robots == 0:
            return
        k = self.kernels
        args = (self.vr, self.vi, self.lr, self.li, self.rt, self.ri, self.mt, self.lt, self.gp)
        flags = (int(self.config.floor), self.ifx, self.dyn)
        if self.schedule == "robots":
            k.run_robots(*args, n_steps, *flags, self._queue, self._workers)
        else:
            left = n_steps
            while left > 0:
                k.run_flat(*args, min(left, UNROLL), *flags)
                left -= UNROLL
        self.steps_done += n_steps

    def set_velocity(self, velocity: np.ndarray, release_static: bool = True) -> None:
        """Overwrite every voxel's linear velocity (float ``[n, 3]``, m/s), e.g. to launch a settled block.

        release_static: also clear the floor static-friction state (a static voxel ignores its momentum).
        """
        velocity = np.asarray(velocity, dtype=np.float64)
        if velocity.shape != (self.layout.num_voxels, 3):
            raise ValueError(f"velocity must have shape {(self.layout.num_voxels, 3)}, got {velocity.shape}")
        vr = self._download(self.vr)
        mass = material_table(self.config)[1][self.layout.material]
        vr[VR.MOM:VR.MOM + 3, : self.layout.num_voxels] = (velocity * mass[:, None]).T
        self.vr = self._upload(np.ascontiguousarray(vr))
        if release_static:
            vi = self._download(self.vi)
            vi[VI.FLAGS] &= ~STATIC
            self.vi = self._upload(np.ascontiguousarray(vi))

    # ------------------------------------------------------------------ reading state (host copies)
    def voxel_state(self) -> np.ndarray:
        """float ``[NVR, n]`` (see ``kernels.VR`` for the columns)."""
        return self._download(self.vr)[:, : self.layout.num_voxels]

    def positions(self) -> np.ndarray:
        """Voxel centres, float64 ``[n, 3]`` (m; robot frame = world frame, floor plane at z = −L/2)."""
        return self.voxel_state()[VR.POS:VR.POS + 3].T.astype(np.float64)

    def orientations(self) -> np.ndarray:
        """Voxel orientation quaternions (w, x, y, z), float64 ``[n, 4]``."""
        return self.voxel_state()[VR.ORI:VR.ORI + 4].T.astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Linear velocities, float64 ``[n, 3]``."""
        mass = material_table(self.config)[1][self.layout.material]
        return self.voxel_state()[VR.MOM:VR.MOM + 3].T.astype(np.float64) / mass[:, None]

    def link_strain(self) -> np.ndarray:
        """Axial strain of every link at its last update, float64 ``[m]``."""
        return self._download(self.lr)[LR.STRAIN, : self.layout.num_links].astype(np.float64)

    def static_friction(self) -> np.ndarray:
        """Floor static-friction state per voxel, bool ``[n]``."""
        return (self._download(self.vi)[VI.FLAGS, : self.layout.num_voxels] & STATIC) != 0

    def robot_status(self) -> np.ndarray:
        """int32 ``[R]``: RUNNING, DONE or DIVERGED."""
        return self._download(self.ri)[RI.STATUS, : self.layout.num_robots]

    def robot_steps(self) -> np.ndarray:
        return self._download(self.ri)[RI.STEP, : self.layout.num_robots].astype(np.int64)

    def robot_time(self) -> np.ndarray:
        return self._download(self.rt)[RT.T, : self.layout.num_robots]

    def robot_dt(self) -> np.ndarray:
        return self._download(self.rt)[RT.DT, : self.layout.num_robots]


def _pad(a: np.ndarray) -> np.ndarray:
    if a.shape[1] > 0:
        return a
    return np.zeros((a.shape[0], 1), dtype=a.dtype)
