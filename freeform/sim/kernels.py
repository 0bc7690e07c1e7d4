"""Voxelyze's link and voxel updates as Taichi functions, and the two schedules that drive them.

Data layout: every state array is a table of named columns (below) in one of two memory orders (``make_kernels``):
"soa" ``[columns, items]`` (item i of column c at ``c·items + i``: neighbouring threads read neighbouring
addresses; the GPU's flat schedule) or "aos", a 1-D ndarray of ``columns``-vectors (one item's columns together,
row length known at compile time; the CPU's per-robot schedule). Only ``ld/st/get3/set3`` know the order.

* ``vr`` real, NVR columns × n voxels: voxel state; ``vi`` int32, NVI × n: voxel topology/flags,
* ``lr`` real, NLR × m links: link state; ``li`` int32, NLI × m: link topology/flags,
* ``rt`` float64, NRT × R robots: robot clocks; ``ri`` int32, NRI × R: robot status, ranges and step events,
* ``mt`` real material table, ``lt`` real link-material table (``config.MAT_COLUMNS`` / ``LINK_COLUMNS``),
* ``gp`` float64 ``[NGP]`` global parameters.

One step = every link's ``link_update`` (forces into fixed per-link slots), then every voxel's
``voxel_update`` (gathers its ≤ 6 links' forces: no atomics, deterministic), then every robot's clock.
Schedules: ``run_flat`` is one thread per link / voxel / robot and ``UNROLL`` steps per launch (GPU);
``run_robots`` has one worker per CPU thread, each taking whole robots from an atomic queue and running them many
steps per launch (no per-step thread-pool synchronisation, the robot's data stays in cache). Both call the same
functions, so they compute the same thing (bit for bit up to the compiler's fast-math reassociation).

Precision: with f64 the arithmetic follows VX (acos rotation vector, quaternions never renormalised, pow); with
f32 orientations are renormalised every step and rotation vectors use atan2 (spec section 14), with series
shortcuts exact to f32 rounding where they are cheaper (see the constants below and docs/physics.md).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
import math
from types import SimpleNamespace

import taichi as ti

from freeform.sim.config import LINK_COLUMNS, MAT_COLUMNS, POISSON_SERIES_TERMS


def _columns(*spec: tuple[str, int]) -> tuple[SimpleNamespace, int]:
    ns, at = {}, 0
    for name, width in spec:
        ns[name] = at
        at += width
    return SimpleNamespace(**ns), at


# voxel real columns: position, linear momentum, orientation (w,x,y,z), angular momentum, original position,
# transverse area and strain sum for a link along each axis (from the Poisson strains, cached for the next link
# update), rest size L·(1 + T·CTE) at the temperature in effect, constant temperature,
# snapshots at the evaluation start/end, last centre-of-mass sample, and that sample at the start/end.
VR, NVR = _columns(("POS", 3), ("MOM", 3), ("ORI", 4), ("AMOM", 3), ("POS0", 3), ("TAREA", 3), ("TSUM", 3),
                   ("SIZE", 1), ("TBASE", 1), ("PSTART", 3), ("PEND", 3), ("PSAMP", 3), ("PCS", 3), ("PCE", 3))
VI, NVI = _columns(("MAT", 1), ("ROBOT", 1), ("FLAGS", 1), ("SLOT", 6))
# link real columns: pos2 / angle1v / angle2v of the last step, axial strain, forces and moments on each end
LR, NLR = _columns(("P2", 3), ("A1", 3), ("A2", 3), ("STRAIN", 1), ("FN", 3), ("FP", 3), ("MN", 3), ("MP", 3))
LI, NLI = _columns(("NEG", 1), ("POS", 1), ("AXIS", 1), ("LMAT", 1), ("FLAGS", 1))
# SIN/COS: sin and cos of 2π·τ/period for the temperature the voxels write this step (τ = the time it is for),
# so each voxel evaluates T = T_base + A·(sin·cos φ + cos·sin φ) without a transcendental call of its own.
RT, NRT = _columns(("T", 1), ("DT", 1), ("DTPREV", 1), ("OMEGA2", 1), ("SIN", 1), ("COS", 1))
# EVENTS: what the coming step's voxel update snapshots (EV_* bits), decided once per robot per step
RI, NRI = _columns(("STATUS", 1), ("STEP", 1), ("VSTART", 1), ("VEND", 1), ("LSTART", 1), ("LEND", 1),
                   ("PERIOD", 1), ("EVENTS", 1))
GP, NGP = _columns(("BURN_IN", 1), ("T_END", 1), ("GRAVITY", 1), ("TEMP_AMP", 1), ("TEMP_PERIOD", 1),
                   ("DT_FRAC", 1), ("MAX_STRAIN", 1))
MT = SimpleNamespace(**{c: i for i, c in enumerate(MAT_COLUMNS)})
LT = SimpleNamespace(**{c: i for i, c in enumerate(LINK_COLUMNS)})

# voxel flags
STATIC, FIXED = 1, 2
# link flags
SMALL, VALID = 1, 2
# robot status
RUNNING, DONE, DIVERGED = 0, 1, 2
# robot step events: take a COM sample; the step crosses the evaluation start; it crosses the evaluation end
EV_SAMPLE, EV_START, EV_END = 1, 2, 4

UNROLL = 2  # steps per launch of the flat schedule
ORDERS = ("soa", "aos")
# Taichi 1.7's CPU backend splits a range-for with a runtime bound into one block per thread of at least this
# many iterations (see run_robots); only the CPU schedule's thread count depends on it, never the results.
CPU_MIN_TASK_ITEMS = 512  # memory order of the state arrays (see make_kernels)

# Voxelyze's small/large-angle switch (VX_Link.cpp): enter small below 0.05 rad and 50 % extension, leave above
# 1.2× those (hysteresis). These are part of the model, not tuning knobs.
SA_BOND_BEND_RAD, SA_BOND_EXT_PERC, HYSTERESIS_FACTOR = 0.05, 0.50, 1.2
# Quat3D thresholds (FromRotationVector, ToRotationVector, FromAngleToPosX).
_ROTVEC_SMALL4, _TOROT_SL, _POSX_SMALL, _POSX_PI_EPS = 5.328e-15, 2.4e-3, 1.732e-2, 1e-7
TWO_PI = 2 * math.pi
# f32 rotation vector: below this x² = (|xyz|/w)² (half-angle tan² 0.0256, a 0.32 rad bend) atan's series to x⁶
# is exact to f32 rounding (truncation x⁸/9 < 5e-8).
_ATAN_SERIES_X2 = 0.0256
_RENORM_NEWTON = 1e-4  # f32 renormalisation: |1 − |q|²| below this uses one Newton step (error < 1e-8)
_POISSON_SERIES_X = 0.1  # |Σ tension strains| below which f32 uses the binomial series (config.POISSON_SERIES_TERMS)


@functools.cache
def make_kernels(precision: str, order: str = "soa") -> SimpleNamespace:
    """Compile-once kernel set for "f32" | "f64" (explicit dtypes, so both can live in one process) and an array
    order: "soa" (``[columns, items]``: neighbouring threads read neighbouring addresses; the GPU's) or "aos"
    (``[items, columns]``: one item's columns share cache lines; the CPU's one-thread-per-robot schedule)."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    aos = order == "aos"
    real = ti.f64 if precision == "f64" else ti.f32
    exact_vx = precision == "f64"
    vec3 = ti.types.vector(3, real)
    vec4 = ti.types.vector(4, real)
    big = 1.0e300 if exact_vx else 3.0e38  # anything beyond is treated as non-finite
    ParArr = ti.types.ndarray(dtype=ti.f64, ndim=1)

    def arr(dtype, columns: int):
        """Kernel argument type of a state array: ``[columns, items]`` (soa), or ``[items]`` of ``columns``-vectors
        (aos: the row length is a compile-time constant, so an item's address is computed once, not per access)."""
        if aos:
            return ti.types.ndarray(dtype=ti.types.vector(columns, dtype), ndim=1)
        return ti.types.ndarray(dtype=dtype, ndim=2)

    VrArr, ViArr, LrArr, LiArr = arr(real, NVR), arr(ti.i32, NVI), arr(real, NLR), arr(ti.i32, NLI)
    RtArr, RiArr = arr(ti.f64, NRT), arr(ti.i32, NRI)
    MtArr, LtArr = arr(real, len(MAT_COLUMNS)), arr(real, len(LINK_COLUMNS))

    # ---------------------------------------------------------------- array access (the one place that knows
    # the memory order: column c of item i is a[i, c] in "aos", a[c, i] in "soa")
    @ti.func
    def ld(a: ti.template(), c, i):
        if ti.static(aos):
            return a[i][c]
        else:
            return a[c, i]

    @ti.func
    def st(a: ti.template(), c: ti.template(), i, x):
        if ti.static(aos):
            a[i][c] = x
        else:
            a[c, i] = x

    @ti.func
    def amax(a: ti.template(), c: ti.template(), i, x):
        if ti.static(aos):
            ti.atomic_max(a[i][c], x)
        else:
            ti.atomic_max(a[c, i], x)

    @ti.func
    def items(a: ti.template()):
        if ti.static(aos):
            return a.shape[0]
        else:
            return a.shape[1]

    @ti.func
    def get3(a: ti.template(), c: ti.template(), i):
        return vec3(ld(a, c, i), ld(a, c + 1, i), ld(a, c + 2, i))

    @ti.func
    def set3(a: ti.template(), c: ti.template(), i, x):
        st(a, c, i, x[0])
        st(a, c + 1, i, x[1])
        st(a, c + 2, i, x[2])

    @ti.func
    def get4(a: ti.template(), c: ti.template(), i):
        return vec4(ld(a, c, i), ld(a, c + 1, i), ld(a, c + 2, i), ld(a, c + 3, i))

    @ti.func
    def set4(a: ti.template(), c: ti.template(), i, x):
        st(a, c, i, x[0])
        st(a, c + 1, i, x[1])
        st(a, c + 2, i, x[2])
        st(a, c + 3, i, x[3])

    @ti.func
    def qmul(a, b):
        """Hamilton product a*b ("apply b, then a")."""
        return vec4(
            a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
            a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
            a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
        )

    @ti.func
    def conj(q):
        return vec4(q[0], -q[1], -q[2], -q[3])

    @ti.func
    def rotate(q, f):
        """q f q* in Quat3D::RotateVec3D's arithmetic (also valid for a slightly non-unit q, as in VX)."""
        w, x, y, z = q[0], q[1], q[2], q[3]
        tw = f[0] * x + f[1] * y + f[2] * z
        tx = f[0] * w - f[1] * z + f[2] * y
        ty = f[0] * z + f[1] * w - f[2] * x
        tz = -f[0] * y + f[1] * x + f[2] * w
        return vec3(w * tx + x * tw + y * tz - z * ty, w * ty - x * tz + y * tw + z * tx,
                    w * tz + x * ty - y * tx + z * tw)

    @ti.func
    def to_axis_x(v, axis):
        """Permute a link-axis vector onto +x (VX toAxisX); for a quaternion pass its (x, y, z)."""
        r = v
        if axis == 1:
            r = vec3(v[1], -v[0], v[2])
        elif axis == 2:
            r = vec3(v[2], v[1], -v[0])
        return r

    @ti.func
    def to_axis_original(v, axis):
        r = v
        if axis == 1:
            r = vec3(-v[1], v[0], v[2])
        elif axis == 2:
            r = vec3(-v[2], v[1], v[0])
        return r

    @ti.func
    def q_to_axis_x(q, axis):
        v = to_axis_x(vec3(q[1], q[2], q[3]), axis)
        return vec4(q[0], v[0], v[1], v[2])

    @ti.func
    def to_rotation_vector(q):
        r = vec3(0.0, 0.0, 0.0)
        xyz = vec3(q[1], q[2], q[3])
        if ti.static(exact_vx):
            w = q[0]
            if w < 1.0 and w > -1.0:
                sl = 1.0 - w * w
                if sl < _TOROT_SL:
                    r = 2.0 * xyz * ti.sqrt((2.0 - 2.0 * w) / sl)
                else:
                    r = 2.0 * xyz * ti.acos(w) / ti.sqrt(sl)
        else:
            # atan2 form: no dead zone below ~5e-4 rad where f32 cos(θ/2) rounds to 1 (spec section 14).
            # Links bend by well under 0.3 rad, so the common case uses the series of atan(x)/x in x² = s²/w²
            # (to x⁶: truncation < x⁸/9 ≈ 5e-8 at the cut, below f32 rounding), with no sqrt or atan2 call.
            w = q[0]
            s2 = xyz.dot(xyz)
            if w > 0.0 and s2 < _ATAN_SERIES_X2 * w * w:
                iw = 1.0 / w
                x2 = s2 * iw * iw
                r = (2.0 * iw * (1.0 + x2 * (-1.0 / 3.0 + x2 * (1.0 / 5.0 - x2 * (1.0 / 7.0))))) * xyz
            elif s2 > 0.0:
                s = ti.sqrt(s2)
                r = 2.0 * ti.atan2(s, w) * xyz / s
        return r

    @ti.func
    def from_rotation_vector(v):
        th = 0.5 * v
        a2 = th.dot(th)
        w = ti.cast(1.0, real)
        s = ti.cast(1.0, real)
        if a2 * a2 < _ROTVEC_SMALL4:
            w = 1.0 - a2 / 2.0
            s = 1.0 - a2 / 6.0
        else:
            a = ti.sqrt(a2)
            w = ti.cos(a)
            s = ti.sin(a) / a
        return vec4(w, th[0] * s, th[1] * s, th[2] * s)

    @ti.func
    def from_angle_to_pos_x(p):
        """The rotation that takes p onto +x (Quat3D::FromAngleToPosX); identity for p = 0."""
        q = vec4(1.0, 0.0, 0.0, 0.0)
        if not (p[0] == 0.0 and p[1] == 0.0 and p[2] == 0.0):
            if p[0] != 0.0 and ti.abs(p[1] / p[0]) < _POSX_SMALL and ti.abs(p[2] / p[0]) < _POSX_SMALL:
                y = 0.5 * p[2] / p[0]
                z = -0.5 * p[1] / p[0]
                q = vec4(1.0 - 0.5 * (y * y + z * z), 0.0, y, z)
            else:
                n = p / p.norm()
                th = ti.acos(ti.min(ti.max(n[0], -1.0), 1.0))
                if th > math.pi - _POSX_PI_EPS:
                    q = vec4(0.0, 0.0, 1.0, 0.0)
                else:
                    s = ti.sin(0.5 * th)
                    yz = ti.sqrt(n[1] * n[1] + n[2] * n[2])
                    q = vec4(ti.cos(0.5 * th), 0.0, n[2] * s / yz, -n[1] * s / yz)
        return q

    @ti.func
    def base_size(mt: ti.template(), mat, temp):
        """Rest size of a voxel along any axis: L·(1 + T·CTE) (extScale = 1)."""
        return ld(mt, MT.L, mat) * (1.0 + temp * ld(mt, MT.CTE, mat))

    @ti.func
    def temperature(mt: ti.template(), rt: ti.template(), gp: ti.template(), mat, tbase, r):
        """T(τ) = T_base + A·sin(2π(τ/period + φ)), φ in cycles; sin/cos of 2πτ/period come from the robot."""
        s = ti.cast(ld(rt, RT.SIN, r), real) * ld(mt, MT.COSPHI, mat) + ti.cast(ld(rt, RT.COS, r), real) * ld(mt, MT.SINPHI, mat)
        return tbase + ti.cast(gp[GP.TEMP_AMP], real) * s

    @ti.func
    def set_phase(r, rt: ti.template(), gp: ti.template(), tau):
        a = TWO_PI * tau / gp[GP.TEMP_PERIOD]
        st(rt, RT.SIN, r, ti.sin(a))
        st(rt, RT.COS, r, ti.cos(a))

    @ti.func
    def transverse(mt: ti.template(), mat, ps):
        """Transverse areas and strain sums (VX_Voxel.cpp) for a link along x, y, z from the voxel's Poisson
        strains ``ps``: two vec3, computed once per voxel per step rather than by each of its ≤ 6 links."""
        L = ld(mt, MT.L, mat)
        area = vec3(L * L, L * L, L * L)
        ssum = vec3(0.0, 0.0, 0.0)
        if ld(mt, MT.NU, mat) != 0.0:
            area = vec3(L * L * (1.0 + ps[1]) * (1.0 + ps[2]), L * L * (1.0 + ps[0]) * (1.0 + ps[2]),
                        L * L * (1.0 + ps[0]) * (1.0 + ps[1]))
            ssum = vec3(ps[1] + ps[2], ps[0] + ps[2], ps[0] + ps[1])
        return area, ssum

    # ---------------------------------------------------------------- the link update (spec section 5)
    @ti.func
    def link_update(lk, vr: ti.template(), vi: ti.template(), lr: ti.template(), li: ti.template(),
                    rt: ti.template(), ri: ti.template(), mt: ti.template(), lt: ti.template(),
                    gp: ti.template(), ifx: ti.template(), dyn: ti.template()):
        n, p, axis, k = ld(li, LI.NEG, lk), ld(li, LI.POS, lk), ld(li, LI.AXIS, lk), ld(li, LI.LMAT, lk)
        r = ld(vi, VI.ROBOT, n)
        mat_n, mat_p = ld(vi, VI.MAT, n), ld(vi, VI.MAT, p)
        flags = ld(li, LI.FLAGS, lk)
        small = (flags & SMALL) != 0
        valid = (flags & VALID) != 0
        size_n = ld(vr, VR.SIZE, n)
        L0 = size_n  # rl4design: the negative voxel's size only (the paper simulator's bug, kept on purpose)
        if ti.static(ifx == 0):
            L0 = 0.5 * (size_n + ld(vr, VR.SIZE, p))

        # orientLink: into the link frame, relative to the negative voxel
        q1 = q_to_axis_x(get4(vr, VR.ORI, n), axis)
        q2 = q_to_axis_x(get4(vr, VR.ORI, p), axis)
        R = conj(q1)
        pos2 = rotate(R, to_axis_x(get3(vr, VR.POS, p) - get3(vr, VR.POS, n), axis))
        q2 = qmul(R, q2)
        q1 = vec4(1.0, 0.0, 0.0, 0.0)
        small_turn = (ti.abs(pos2[2]) + ti.abs(pos2[1])) / pos2[0]
        extend = ti.abs(1.0 - pos2[0] / L0)
        leave = small and (small_turn > HYSTERESIS_FACTOR * SA_BOND_BEND_RAD
                           or extend > HYSTERESIS_FACTOR * SA_BOND_EXT_PERC)
        if ti.static(ifx != 0):
            # the paper simulator's precedence slip: `small && a || b`
            leave = (small and small_turn > HYSTERESIS_FACTOR * SA_BOND_BEND_RAD) or \
                extend > HYSTERESIS_FACTOR * SA_BOND_EXT_PERC
        if (not small) and small_turn < SA_BOND_BEND_RAD and extend < SA_BOND_EXT_PERC:
            small = True
            valid = False
        elif leave:
            small = False
            valid = False
        if small:
            pos2[0] -= L0  # the y, z offsets stay and act as shear
        a1v = vec3(0.0, 0.0, 0.0)  # small angle: q1 is the identity
        if not small:
            q1 = from_angle_to_pos_x(pos2)
            q2 = qmul(q1, q2)
            pos2 = vec3(pos2.norm() - L0, 0.0, 0.0)
            a1v = to_rotation_vector(q1)
        a2v = to_rotation_vector(q2)
        strain = pos2[0] / L0
        if ti.static(ifx != 0):
            pos2[0] += L0  # rl4design keeps the raw separation, so its damping sees d, not d − L0

        dP = 0.5 * (pos2 - get3(lr, LR.P2, lk))
        dA1 = 0.5 * (a1v - get3(lr, LR.A1, lk))
        dA2 = 0.5 * (a2v - get3(lr, LR.A2, lk))

        # volume effects: transverse area and strain sum from both voxels' cached Poisson strains
        nu = ld(lt, LT.NU, k)
        area = 0.5 * (ld(vr, VR.TAREA + axis, n) + ld(vr, VR.TAREA + axis, p))
        ssum = 0.5 * (ld(vr, VR.TSUM + axis, n) + ld(vr, VR.TSUM + axis, p))
        stress = ld(lt, LT.E, k) * strain
        if nu != 0.0:
            stress = ld(lt, LT.EHAT, k) * ((1.0 - nu) * strain + nu * ssum)

        b1, b2, b3, a2 = ld(lt, LT.B1, k), ld(lt, LT.B2, k), ld(lt, LT.B3, k), ld(lt, LT.A2, k)
        fN = vec3(stress * area, b1 * pos2[1] - b2 * (a1v[2] + a2v[2]), b1 * pos2[2] + b2 * (a1v[1] + a2v[1]))
        fP = -fN
        mN = vec3(a2 * (a2v[0] - a1v[0]), -b2 * pos2[2] - b3 * (2.0 * a1v[1] + a2v[1]),
                  b2 * pos2[1] - b3 * (2.0 * a1v[2] + a2v[2]))
        mP = vec3(a2 * (a1v[0] - a2v[0]), -b2 * pos2[2] - b3 * (a1v[1] + 2.0 * a2v[1]),
                  b2 * pos2[1] - b3 * (a1v[2] + 2.0 * a2v[2]))

        if valid:
            # internal damping: D = 2·√m·ζ/previousDt of each end's voxel; posCalc are half-link displacements
            prev_dt = ti.cast(ld(rt, RT.DTPREV, r), real)
            dN = ld(mt, MT.DAMP, mat_n) / prev_dt
            dPp = ld(mt, MT.DAMP, mat_p) / prev_dt
            sqA1, sqA2xIp, sqB1 = ld(lt, LT.SQA1, k), ld(lt, LT.SQA2XIP, k), ld(lt, LT.SQB1, k)
            sqB2xFMp, sqB3xIp = ld(lt, LT.SQB2XFMP, k), ld(lt, LT.SQB3XIP, k)
            c = vec3(sqA1 * dP[0], sqB1 * dP[1] - sqB2xFMp * (dA1[2] + dA2[2]),
                     sqB1 * dP[2] + sqB2xFMp * (dA1[1] + dA2[1]))
            fN += dN * c
            fP -= dPp * c
            mN -= 0.5 * dN * vec3(-sqA2xIp * (dA2[0] - dA1[0]), sqB2xFMp * dP[2] + sqB3xIp * (2.0 * dA1[1] + dA2[1]),
                                  -sqB2xFMp * dP[1] + sqB3xIp * (2.0 * dA1[2] + dA2[2]))
            mP -= 0.5 * dPp * vec3(sqA2xIp * (dA2[0] - dA1[0]), sqB2xFMp * dP[2] + sqB3xIp * (dA1[1] + 2.0 * dA2[1]),
                                   -sqB2xFMp * dP[1] + sqB3xIp * (dA1[2] + 2.0 * dA2[2]))
        else:
            valid = True  # damping resumes next step

        # back into each voxel's local frame
        if not small:
            qc = conj(q1)
            fN = rotate(qc, fN)
            mN = rotate(qc, mN)
        q2c = conj(q2)
        fP = rotate(q2c, fP)
        mP = rotate(q2c, mP)
        set3(lr, LR.FN, lk, to_axis_original(fN, axis))
        set3(lr, LR.FP, lk, to_axis_original(fP, axis))
        set3(lr, LR.MN, lk, to_axis_original(mN, axis))
        set3(lr, LR.MP, lk, to_axis_original(mP, axis))
        set3(lr, LR.P2, lk, pos2)
        set3(lr, LR.A1, lk, a1v)
        set3(lr, LR.A2, lk, a2v)
        st(lr, LR.STRAIN, lk, strain)
        st(li, LI.FLAGS, lk, (SMALL if small else 0) | (VALID if valid else 0))

        if not (strain <= gp[GP.MAX_STRAIN]):  # also catches NaN
            st(ri, RI.STATUS, r, DIVERGED)
        if ti.static(dyn != 0):
            if (ld(ri, RI.STEP, r) + 1) % 10 == 0:
                # rl4design recomputes dt every 10 steps from the current axial stiffness (VX_Link::axialStiffness)
                kax = ld(lt, LT.A1, k)
                if nu != 0.0:
                    kax = ld(lt, LT.EHAT, k) * area / ((strain + 1.0) * L0)
                mmin = ti.min(ld(mt, MT.MASS, mat_n), ld(mt, MT.MASS, mat_p))
                amax(rt, RT.OMEGA2, r, ti.cast(kax / mmin, ti.f64))

    # ---------------------------------------------------------------- the voxel update (spec sections 6-9)
    @ti.func
    def voxel_update(v, vr: ti.template(), vi: ti.template(), lr: ti.template(), li: ti.template(),
                     rt: ti.template(), ri: ti.template(), mt: ti.template(), lt: ti.template(),
                     gp: ti.template(), floor: ti.template(), ifx: ti.template()):
        r = ld(vi, VI.ROBOT, v)
        mat = ld(vi, VI.MAT, v)
        flags = ld(vi, VI.FLAGS, v)
        dt = ti.cast(ld(rt, RT.DT, r), real)
        minv, iinv = ld(mt, MT.MINV, mat), ld(mt, MT.IINV, mat)
        pos = get3(vr, VR.POS, v)
        mom = get3(vr, VR.MOM, v)
        q = get4(vr, VR.ORI, v)
        amom = get3(vr, VR.AMOM, v)
        size = ld(vr, VR.SIZE, v)  # the rest size at the start of the step

        # Poisson strain of this voxel from its links' strains of this step, cached for the next link update
        # (VX computes it lazily at the next step's first link; nothing has changed by then: a Jacobi update).
        s = vec3(0.0, 0.0, 0.0)
        nu = ld(mt, MT.NU, mat)
        if nu != 0.0:
            tension = ti.Vector([0, 0, 0])
            for a in ti.static(range(3)):
                cnt = 0
                for side in ti.static(range(2)):
                    lk = ld(vi, VI.SLOT + 2 * a + side, v)
                    if lk >= 0:
                        eps = ld(lr, LR.STRAIN, lk)
                        if ti.static(side == 1):  # a NEG slot: this voxel is the link's positive end
                            s[a] += eps * ld(lt, LT.PSPOS, ld(li, LI.LMAT, lk))
                        else:
                            s[a] += eps * ld(lt, LT.PSNEG, ld(li, LI.LMAT, lk))
                        cnt += 1
                if cnt == 2:
                    s[a] *= 0.5
                    tension[a] = 1
            if not (tension[0] == 1 and tension[1] == 1 and tension[2] == 1):
                add = ti.cast(0.0, real)
                for a in ti.static(range(3)):
                    if tension[a] == 1:
                        add += s[a]
                val = ti.cast(0.0, real)
                if ti.static(exact_vx):
                    val = ti.pow(1.0 + add, -nu) - 1.0
                else:
                    # f32: (1+x)^(−ν) − 1 by its binomial series where it converges fast (|x| < 0.1: truncation
                    # < 3e-9 relative, 20× below f32 rounding of the result), else powf. Cheaper than the libm call,
                    # which was ~10 % of a CPU step on design bodies (mostly surface voxels), and no 1 − 1 cancellation.
                    if ti.abs(add) < _POISSON_SERIES_X:
                        c = ld(mt, MT.PB1 + POISSON_SERIES_TERMS - 1, mat)
                        for k in ti.static(range(POISSON_SERIES_TERMS - 1, 0, -1)):
                            c = ld(mt, MT.PB1 + k - 1, mat) + add * c
                        val = add * c
                    else:
                        val = ti.pow(1.0 + add, -nu) - 1.0
                for a in ti.static(range(3)):
                    if tension[a] == 0:
                        s[a] = val

        if (flags & FIXED) != 0:
            # held in all 6 DOF (VX isFixedAll): back to the original pose, no motion
            pos = get3(vr, VR.POS0, v)
            mom = vec3(0.0, 0.0, 0.0)
            amom = vec3(0.0, 0.0, 0.0)
            q = vec4(1.0, 0.0, 0.0, 0.0)
        else:
            force = vec3(0.0, 0.0, 0.0)
            moment = vec3(0.0, 0.0, 0.0)
            for d in ti.static(range(6)):
                lk = ld(vi, VI.SLOT + d, v)
                if lk >= 0:
                    if ti.static(d % 2 == 1):  # NEG slot: this voxel is the link's positive end
                        force += get3(lr, LR.FP, lk)
                        moment += get3(lr, LR.MP, lk)
                    else:
                        force += get3(lr, LR.FN, lk)
                        moment += get3(lr, LR.MN, lk)
            vel = mom * minv
            force = rotate(q, force) - ld(mt, MT.CG, mat) * vel
            force[2] += ld(mt, MT.MG, mat)
            moment = rotate(q, moment) - ld(mt, MT.CGR, mat) * (amom * iinv)

            # floor contact (pen at the start of the step) and Coulomb friction with the static/kinetic states
            static = (flags & STATIC) != 0
            pen = 0.5 * size - 0.5 * ld(mt, MT.L, mat) - pos[2]
            fric = vec3(0.0, 0.0, 0.0)
            if ti.static(floor != 0):
                if pen >= 0.0:
                    normal = ld(mt, MT.KPEN, mat) * pen
                    force[2] += normal - ld(mt, MT.CC, mat) * vel[2]
                    if static:
                        mus = ld(mt, MT.MUS, mat) * normal
                        if force[0] * force[0] + force[1] * force[1] > mus * mus:
                            static = False  # breaks loose; the full force acts this step
                    else:
                        vh = ti.sqrt(vel[0] * vel[0] + vel[1] * vel[1])
                        if vh > 0.0:
                            f = ld(mt, MT.MUK, mat) * normal / vh
                            fric = vec3(-f * vel[0], -f * vel[1], 0.0)
                            force += fric
                else:
                    static = False
            mom += force * dt
            delta = mom * (dt * minv)
            touching = False
            if ti.static(floor != 0):
                touching = pen >= 0.0
            if touching:
                # work-energy stop test: friction would reverse the horizontal motion within this step
                work = fric[0] * delta[0] + fric[1] * delta[1]
                hke = 0.5 * (mom[0] * mom[0] + mom[1] * mom[1]) * minv
                if hke + work <= 0.0:
                    static = True
                if static:
                    mom[0] = 0.0
                    mom[1] = 0.0
                    delta[0] = 0.0
                    delta[1] = 0.0
            else:
                static = False
            pos += delta
            amom += moment * dt
            q = qmul(from_rotation_vector(amom * (dt * iinv)), q)
            if ti.static(not exact_vx):
                # |q|² = 1 + e with e at rounding level (the update rotation is unit): one Newton step of 1/√ from
                # 1, (3 − |q|²)/2, is exact to O(e²); the sqrt and division stay for anything further off
                n2 = q.dot(q)
                if ti.abs(n2 - 1.0) < _RENORM_NEWTON:
                    q = q * (1.5 - 0.5 * n2)
                else:
                    q = q * (1.0 / ti.sqrt(n2))
            if ti.static(ifx != 0 and floor != 0):
                if static and 0.5 * size - 0.5 * ld(mt, MT.L, mat) - pos[2] >= 0.0:
                    amom = vec3(0.0, 0.0, 0.0)  # rl4design zeroes spin in static floor contact
            flags = (flags & ~STATIC) | (STATIC if static else 0)

        # (an L1 norm: no sqrt, and NaN or inf anywhere still fails the comparison)
        if not (ti.abs(pos[0]) + ti.abs(pos[1]) + ti.abs(pos[2]) + ti.abs(amom[0]) + ti.abs(amom[1])
                + ti.abs(amom[2]) < big):
            st(ri, RI.STATUS, r, DIVERGED)

        set3(vr, VR.POS, v, pos)
        set3(vr, VR.MOM, v, mom)
        set4(vr, VR.ORI, v, q)
        set3(vr, VR.AMOM, v, amom)
        area, ssum = transverse(mt, mat, s)
        set3(vr, VR.TAREA, v, area)
        set3(vr, VR.TSUM, v, ssum)
        st(vi, VI.FLAGS, v, flags)
        # temperature for the next step: VX sets T(t) before each step; rl4design writes T(t) after the
        # voxel update, so its links lag one step behind (the robot's SIN/COS hold the right τ for each)
        st(vr, VR.SIZE, v, base_size(mt, mat, temperature(mt, rt, gp, mat, ld(vr, VR.TBASE, v), r)))

        # snapshots: COM samples every PERIOD steps; evaluation start/end at the first step past each time
        # (which of these this step takes was decided once for the robot, by robot_advance or the Engine)
        events = ld(ri, RI.EVENTS, r)
        if events != 0:
            if (events & EV_SAMPLE) != 0:
                set3(vr, VR.PSAMP, v, pos)
            if (events & EV_START) != 0:
                set3(vr, VR.PSTART, v, pos)
                set3(vr, VR.PCS, v, get3(vr, VR.PSAMP, v))
            if (events & EV_END) != 0:
                set3(vr, VR.PEND, v, pos)
                set3(vr, VR.PCE, v, get3(vr, VR.PSAMP, v))

    @ti.func
    def robot_advance(r, rt: ti.template(), ri: ti.template(), gp: ti.template(), dyn: ti.template(),
                      ifx: ti.template()):
        """End of a step for robot r: clock, status, rl4design's dt refresh every 10 steps, actuation phase."""
        st(rt, RT.DTPREV, r, ld(rt, RT.DT, r))
        st(rt, RT.T, r, ld(rt, RT.T, r) + ld(rt, RT.DT, r))  # (not `+=`: on global data that is an atomic add)
        step = ld(ri, RI.STEP, r) + 1
        st(ri, RI.STEP, r, step)
        if ld(rt, RT.T, r) > gp[GP.T_END] and ld(ri, RI.STATUS, r) == RUNNING:
            st(ri, RI.STATUS, r, DONE)
        if ti.static(dyn != 0):
            if step % 10 == 0:
                if ld(rt, RT.OMEGA2, r) > 0.0:
                    st(rt, RT.DT, r, gp[GP.DT_FRAC] / (TWO_PI * ti.sqrt(ld(rt, RT.OMEGA2, r))))
                st(rt, RT.OMEGA2, r, 0.0)
        # next step the voxels write T(t + dt) (VX) or T(t) (rl4design, one step late)
        tau = ld(rt, RT.T, r) + ld(rt, RT.DT, r)
        if ti.static(ifx != 0):
            tau = ld(rt, RT.T, r)
        set_phase(r, rt, gp, tau)
        # the next step's snapshots, with the same f64 clock arithmetic as Engine's for step 0
        t_before = ld(rt, RT.T, r)
        t_after = t_before + ld(rt, RT.DT, r)
        events = 0
        if (step + 1) % ld(ri, RI.PERIOD, r) == 0:
            events |= EV_SAMPLE
        if t_before <= gp[GP.BURN_IN] and t_after > gp[GP.BURN_IN]:
            events |= EV_START
        if t_before <= gp[GP.T_END] and t_after > gp[GP.T_END]:
            events |= EV_END
        st(ri, RI.EVENTS, r, events)

    # ---------------------------------------------------------------- schedules
    @ti.kernel
    def run_robots(vr: VrArr, vi: ViArr, lr: LrArr, li: LiArr, rt: RtArr, ri: RiArr, mt: MtArr,
                   lt: LtArr, gp: ParArr, n_steps: ti.i32, floor: ti.template(), ifx: ti.template(),
                   dyn: ti.template(), queue: ti.types.ndarray(dtype=ti.i32, ndim=1), workers: ti.i32):
        """``workers`` threads each take the next unclaimed robot from ``queue`` and run it ``n_steps`` steps,
        until none is left (CPU schedule: dynamic load balance over robots of any size, no per-step barrier).

        Why not ``for r in range(R)``: Taichi's CPU backend gives each thread a block of at least
        ``CPU_MIN_TASK_ITEMS`` iterations of a range-for with a runtime bound (``loop_config(block_dim)`` is not
        honoured there), so a batch of fewer robots than that would run on one thread. Each worker therefore owns
        one such block of a virtual range, and the robots are handed out through an atomic counter.
        """
        queue[0] = 0  # (a top-level statement: runs before the parallel loop, as a serial task)
        for t in range(workers * CPU_MIN_TASK_ITEMS):
            if t % CPU_MIN_TASK_ITEMS == 0:
                r = ti.atomic_add(queue[0], 1)
                while r < items(ri):
                    for _ in range(n_steps):
                        if ld(ri, RI.STATUS, r) == RUNNING:
                            for lk in range(ld(ri, RI.LSTART, r), ld(ri, RI.LEND, r)):
                                link_update(lk, vr, vi, lr, li, rt, ri, mt, lt, gp, ifx, dyn)
                            if ld(ri, RI.STATUS, r) == RUNNING:  # a diverged link aborts the step, as in VX
                                for v in range(ld(ri, RI.VSTART, r), ld(ri, RI.VEND, r)):
                                    voxel_update(v, vr, vi, lr, li, rt, ri, mt, lt, gp, floor, ifx)
                            if ld(ri, RI.STATUS, r) == RUNNING:
                                robot_advance(r, rt, ri, gp, dyn, ifx)
                    r = ti.atomic_add(queue[0], 1)

    @ti.kernel
    def run_flat(vr: VrArr, vi: ViArr, lr: LrArr, li: LiArr, rt: RtArr, ri: RiArr, mt: MtArr,
                 lt: LtArr, gp: ParArr, n_steps: ti.i32, floor: ti.template(), ifx: ti.template(),
                   dyn: ti.template()):
        """One thread per link, then per voxel, then per robot; ``min(n_steps, UNROLL)`` steps per launch."""
        for s in ti.static(range(UNROLL)):
            for lk in range(items(li)):
                # (a batch without links carries one padding column with NEG == POS: skip it)
                if s < n_steps and ld(li, LI.NEG, lk) != ld(li, LI.POS, lk) and \
                        ld(ri, RI.STATUS, ld(vi, VI.ROBOT, ld(li, LI.NEG, lk))) == RUNNING:
                    link_update(lk, vr, vi, lr, li, rt, ri, mt, lt, gp, ifx, dyn)
            for v in range(items(vi)):
                if s < n_steps and ld(ri, RI.STATUS, ld(vi, VI.ROBOT, v)) == RUNNING:
                    voxel_update(v, vr, vi, lr, li, rt, ri, mt, lt, gp, floor, ifx)
            for r in range(items(ri)):
                if s < n_steps and ld(ri, RI.STATUS, r) == RUNNING:
                    robot_advance(r, rt, ri, gp, dyn, ifx)

    @ti.kernel
    def probe_rotations(q: ti.types.ndarray(dtype=vec4, ndim=1), rotvec: ti.types.ndarray(dtype=vec3, ndim=1),
                        back: ti.types.ndarray(dtype=vec4, ndim=1)):
        """Test hook: ToRotationVector of each q, and FromRotationVector of that (the kernels' own functions)."""
        for i in range(q.shape[0]):
            rotvec[i] = to_rotation_vector(q[i])
            back[i] = from_rotation_vector(rotvec[i])

    return SimpleNamespace(run_robots=run_robots, run_flat=run_flat, probe_rotations=probe_rotations, real=real,
                           order=order)
