"""The link update (spec section 5, ``CVX_Link::updateForces``): one beam between two face-adjacent voxels.

A link reads both voxels' poses and cached Poisson terms, and writes the force and moment on each end into its
own columns (``LR.FN/FP/MN/MP``, in each voxel's local frame); the voxel update gathers them through fixed slots,
so no atomics are needed and results are deterministic.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
from types import SimpleNamespace

from freeform.sim.access import make_access, make_numbers
from freeform.sim.quat import make_quat
from freeform.sim.runtime import ti
from freeform.sim.state import DIVERGED, GP, LI, LR, LT, MT, RI, RT, SMALL, VALID, VI, VR

# Voxelyze's small/large-angle switch (VX_Link.cpp): enter small below 0.05 rad and 50 % extension, leave above
# 1.2× those (hysteresis). These are part of the model, not tuning knobs.
SA_BOND_BEND_RAD, SA_BOND_EXT_PERC, HYSTERESIS_FACTOR = 0.05, 0.50, 1.2
# rl4design recomputes dt every this many steps (the paper simulator's constant)
DT_REFRESH_STEPS = 10


@functools.cache
def make_links(precision: str, order: str) -> SimpleNamespace:
    """``link_update`` for "f32" | "f64" and memory order "soa" | "aos"."""
    num = make_numbers(precision)
    acc = make_access(precision, order)
    q = make_quat(precision)
    real, vec3, vec4, nonfinite = num.real, num.vec3, num.vec4, num.nonfinite
    ld, st, get3, set3, get4 = acc.ld, acc.st, acc.get3, acc.set3, acc.get4
    qmul, conj, rotate = q.qmul, q.conj, q.rotate
    to_axis_x, to_axis_original, q_to_axis_x = q.to_axis_x, q.to_axis_original, q.q_to_axis_x
    to_rotation_vector, from_angle_to_pos_x = q.to_rotation_vector, q.from_angle_to_pos_x

    # Each step below is one part of Voxelyze's CVX_Link::updateForces (spec section 5); link_update runs them in
    # order. The arithmetic is the source's, in its order (the strict path's bits depend on it).

    @ti.func
    def rest_length(s: ti.template(), n, p):
        """L0 (spec 4): ½(size_N + size_P) of the two voxels' current rest sizes; rl4design: the negative voxel's
        size only (the paper simulator's bug, kept on purpose)."""
        size_n = ld(s.vr, VR.SIZE, n)
        L0 = size_n
        if ti.static(s.sw.rl4design == 0):
            L0 = 0.5 * (size_n + ld(s.vr, VR.SIZE, p))
        return L0

    @ti.func
    def into_link_frame(s: ti.template(), n, p, axis: ti.template()):
        """orientLink's start (spec 5.1): both poses permuted onto +x (toAxisX) and expressed relative to the
        negative voxel, R = conj(q_N): p = Rotate(R, pos_P − pos_N), q2 = R·q_P (q1 becomes the identity)."""
        q1 = q_to_axis_x(get4(s.vr, VR.ORI, n), axis)
        q2 = q_to_axis_x(get4(s.vr, VR.ORI, p), axis)
        R = conj(q1)
        pos2 = rotate(R, to_axis_x(get3(s.vr, VR.POS, p) - get3(s.vr, VR.POS, n), axis))
        q2 = qmul(R, q2)
        return pos2, q2

    @ti.func
    def transverse_terms(s: ti.template(), n, p, axis: ti.template()):
        """Volume effects (spec 5.3): the transverse area A_t and strain sum S_t, the means of both voxels' cached
        Poisson terms for this axis."""
        area = 0.5 * (ld(s.vr, VR.TAREA + axis, n) + ld(s.vr, VR.TAREA + axis, p))
        ssum = 0.5 * (ld(s.vr, VR.TSUM + axis, n) + ld(s.vr, VR.TSUM + axis, p))
        return area, ssum

    @ti.func
    def angle_regime(s: ti.template(), pos2, L0, small, valid):
        """Voxelyze's small/large-angle switch with hysteresis (spec 5.1): SmallTurn = (|p.z| + |p.y|)/p.x and
        ExtendPerc = |1 − p.x/L0|. After a switch the rates below would compare poses from the two paths, so the
        velocity is invalid: no damping this step."""
        small_turn = (ti.abs(pos2[2]) + ti.abs(pos2[1])) / pos2[0]
        extend = ti.abs(1.0 - pos2[0] / L0)
        leave = small and (small_turn > HYSTERESIS_FACTOR * SA_BOND_BEND_RAD
                           or extend > HYSTERESIS_FACTOR * SA_BOND_EXT_PERC)
        if ti.static(s.sw.rl4design != 0):
            # the paper simulator's precedence slip: `small && a || b`
            leave = (small and small_turn > HYSTERESIS_FACTOR * SA_BOND_BEND_RAD) or \
                extend > HYSTERESIS_FACTOR * SA_BOND_EXT_PERC
        if (not small) and small_turn < SA_BOND_BEND_RAD and extend < SA_BOND_EXT_PERC:
            small = True
            valid = False
        elif leave:
            small = False
            valid = False
        return small, valid

    @ti.func
    def beam_deformation(pos2, q2, L0, small):
        """orientLink's end (spec 5.1): the beam's deformation in the link frame. Small angle: p.x −= L0, the y, z
        offsets stay and act as shear, q1 the identity; large angle: q1 = FromAngleToPosX(p) turns the link onto
        +x, q2 = q1·q2, p = (|p| − L0, 0, 0). Returns (p, q1, q2, a1v, a2v), a1v and a2v the rotation vectors of
        the two ends."""
        q1 = vec4(1.0, 0.0, 0.0, 0.0)
        if small:
            pos2[0] -= L0
        a1v = vec3(0.0, 0.0, 0.0)  # small angle: q1 is the identity
        if not small:
            q1 = from_angle_to_pos_x(pos2)
            q2 = qmul(q1, q2)
            pos2 = vec3(pos2.norm() - L0, 0.0, 0.0)
            a1v = to_rotation_vector(q1)
        a2v = to_rotation_vector(q2)
        return pos2, q1, q2, a1v, a2v

    @ti.func
    def axial_stress(s: ti.template(), k, strain, ssum):
        """σ (spec 5.4, VX_Material::stress, linear): E·ε without Poisson effects, else Ê·((1 − ν)ε + ν·S_t)."""
        nu = ld(s.lt, LT.NU, k)
        stress = ld(s.lt, LT.E, k) * strain
        if nu != 0.0:
            stress = ld(s.lt, LT.EHAT, k) * ((1.0 - nu) * strain + nu * ssum)
        return stress

    @ti.func
    def elastic_loads(s: ti.template(), k, axial, pos2, a1v, a2v):
        """The beam's elastic force and moment on each end in the link frame (spec 5.5): ``axial`` = σ·A_t along
        x; shear and bending from the offsets and end rotations (b1 = 12EI/ℓ³, b2 = 6EI/ℓ², b3 = 2EI/ℓ); torsion
        (a2 = GJ/ℓ). Returns (F_N, F_P, M_N, M_P)."""
        b1, b2, b3, a2 = ld(s.lt, LT.B1, k), ld(s.lt, LT.B2, k), ld(s.lt, LT.B3, k), ld(s.lt, LT.A2, k)
        fN = vec3(axial, b1 * pos2[1] - b2 * (a1v[2] + a2v[2]), b1 * pos2[2] + b2 * (a1v[1] + a2v[1]))
        fP = -fN
        mN = vec3(a2 * (a2v[0] - a1v[0]), -b2 * pos2[2] - b3 * (2.0 * a1v[1] + a2v[1]),
                  b2 * pos2[1] - b3 * (2.0 * a1v[2] + a2v[2]))
        mP = vec3(a2 * (a1v[0] - a2v[0]), -b2 * pos2[2] - b3 * (a1v[1] + 2.0 * a2v[1]),
                  b2 * pos2[1] - b3 * (a1v[2] + 2.0 * a2v[2]))
        return fN, fP, mN, mP

    @ti.func
    def bond_damping(s: ti.template(), k, r, mat_n, mat_p, dP, dA1, dA2, fN, fP, mN, mP):
        """Internal damping (spec 5.6) added to the elastic loads: each end's D = 2·√m·ζ/previousDt (its own
        material) times the beam's damping constants on the half-link displacements dP, dA1, dA2 of this step."""
        prev_dt = ti.cast(ld(s.rt, RT.DTPREV, r), real)
        dN = ld(s.mt, MT.DAMP, mat_n) / prev_dt
        dPp = ld(s.mt, MT.DAMP, mat_p) / prev_dt
        sqA1, sqA2xIp, sqB1 = ld(s.lt, LT.SQA1, k), ld(s.lt, LT.SQA2XIP, k), ld(s.lt, LT.SQB1, k)
        sqB2xFMp, sqB3xIp = ld(s.lt, LT.SQB2XFMP, k), ld(s.lt, LT.SQB3XIP, k)
        c = vec3(sqA1 * dP[0], sqB1 * dP[1] - sqB2xFMp * (dA1[2] + dA2[2]),
                 sqB1 * dP[2] + sqB2xFMp * (dA1[1] + dA2[1]))
        fN += dN * c
        fP -= dPp * c
        mN -= 0.5 * dN * vec3(-sqA2xIp * (dA2[0] - dA1[0]), sqB2xFMp * dP[2] + sqB3xIp * (2.0 * dA1[1] + dA2[1]),
                              -sqB2xFMp * dP[1] + sqB3xIp * (2.0 * dA1[2] + dA2[2]))
        mP -= 0.5 * dPp * vec3(sqA2xIp * (dA2[0] - dA1[0]), sqB2xFMp * dP[2] + sqB3xIp * (dA1[1] + 2.0 * dA2[1]),
                               -sqB2xFMp * dP[1] + sqB3xIp * (dA1[2] + 2.0 * dA2[2]))
        return fN, fP, mN, mP

    @ti.func
    def to_voxel_frames(q1, q2, small, fN, fP, mN, mP):
        """The loads in each end's voxel frame, still permuted onto +x (spec 5.7): RotateInv by q1 (large angle
        only: else the identity) and by q2."""
        if not small:
            qc = conj(q1)
            fN = rotate(qc, fN)
            mN = rotate(qc, mN)
        q2c = conj(q2)
        fP = rotate(q2c, fP)
        mP = rotate(q2c, mP)
        return fN, fP, mN, mP

    @ti.func
    def store_end_loads(s: ti.template(), lk, axis: ti.template(), fN, fP, mN, mP):
        """toAxisOriginal (spec 5.7), into the link's own columns, which the voxels gather through fixed slots."""
        set3(s.lr, LR.FN, lk, to_axis_original(fN, axis))
        set3(s.lr, LR.FP, lk, to_axis_original(fP, axis))
        set3(s.lr, LR.MN, lk, to_axis_original(mN, axis))
        set3(s.lr, LR.MP, lk, to_axis_original(mP, axis))

    @ti.func
    def store_omega2(s: ti.template(), lk, k, mat_n, mat_p, L0, strain, area):
        """rl4design's dt refresh: this link's ω² from its current axial stiffness (VX_Link::axialStiffness); the
        robot phase takes the max over the robot's links (clock.py)."""
        nu = ld(s.lt, LT.NU, k)
        kax = ld(s.lt, LT.A1, k)
        if nu != 0.0:
            kax = ld(s.lt, LT.EHAT, k) * area / ((strain + 1.0) * L0)
        st(s.lr, LR.OMEGA2, lk, kax / ti.min(ld(s.mt, MT.MASS, mat_n), ld(s.mt, MT.MASS, mat_p)))

    @ti.func
    def link_update(lk, r, s: ti.template()):
        """Forces and moments of link ``lk`` of robot ``r`` from its voxels' poses (spec 5, steps 1-8); marks the
        robot DIVERGED on a strain above ``max_strain`` or a non-finite one. ``s.sw`` (``state.Switches``): rl4design semantics;
        dynamic_dt: store ω² for the dt refresh.

        What depends on the link's axis (the permutations onto +x and back, the axis's transverse columns) is
        compiled once per axis, so the permutations are register moves and the columns fixed offsets; the beam
        between them is compiled once (links come grouped by axis, so the branch is predictable)."""
        n, p, axis, k = ld(s.li, LI.NEG, lk), ld(s.li, LI.POS, lk), ld(s.li, LI.AXIS, lk), ld(s.li, LI.LMAT, lk)
        mat_n, mat_p = ld(s.vi, VI.MAT, n), ld(s.vi, VI.MAT, p)
        flags = ld(s.li, LI.FLAGS, lk)
        valid = (flags & VALID) != 0
        small = (flags & SMALL) != 0
        L0 = rest_length(s, n, p)

        # 1. orientLink: the deformation in the link frame (x along the link, relative to the negative voxel)
        pos2, q2 = vec3(0.0, 0.0, 0.0), vec4(0.0, 0.0, 0.0, 0.0)
        area, ssum = ti.cast(0.0, real), ti.cast(0.0, real)
        for a in ti.static(range(3)):
            if axis == a:
                pos2, q2 = into_link_frame(s, n, p, a)
                area, ssum = transverse_terms(s, n, p, a)
        small, valid = angle_regime(s, pos2, L0, small, valid)
        pos2, q1, q2, a1v, a2v = beam_deformation(pos2, q2, L0, small)
        strain = pos2[0] / L0
        if ti.static(s.sw.rl4design != 0):
            pos2[0] += L0  # rl4design keeps the raw separation, so its damping sees d, not d − L0

        # 2. half the change since the last step: the displacement of the link's centre relative to each end
        dP = 0.5 * (pos2 - get3(s.lr, LR.P2, lk))
        dA1 = 0.5 * (a1v - get3(s.lr, LR.A1, lk))
        dA2 = 0.5 * (a2v - get3(s.lr, LR.A2, lk))

        # 3.-4. volume effects (the transverse area and strain sum, above), stress
        stress = axial_stress(s, k, strain, ssum)

        # 5.-6. elastic loads, then internal damping unless a regime switch invalidated the rates
        fN, fP, mN, mP = elastic_loads(s, k, stress * area, pos2, a1v, a2v)
        if valid:
            fN, fP, mN, mP = bond_damping(s, k, r, mat_n, mat_p, dP, dA1, dA2, fN, fP, mN, mP)
        else:
            valid = True  # damping resumes next step

        # 7. back into each voxel's local frame; this step's state for the next one
        fN, fP, mN, mP = to_voxel_frames(q1, q2, small, fN, fP, mN, mP)
        for a in ti.static(range(3)):
            if axis == a:
                store_end_loads(s, lk, a, fN, fP, mN, mP)
        set3(s.lr, LR.P2, lk, pos2)
        set3(s.lr, LR.A1, lk, a1v)
        set3(s.lr, LR.A2, lk, a2v)
        st(s.lr, LR.STRAIN, lk, strain)
        st(s.li, LI.FLAGS, lk, (SMALL if small else 0) | (VALID if valid else 0))

        # 8. divergence (every step, every link, as VX)
        if strain > ld(s.gp, GP.MAX_STRAIN, 0) or nonfinite(strain):
            st(s.ri, RI.STATUS, r, DIVERGED)
        if ti.static(s.sw.dynamic_dt != 0):
            if (ld(s.ri, RI.STEP, r) + 1) % DT_REFRESH_STEPS == 0:
                store_omega2(s, lk, k, mat_n, mat_p, L0, strain, area)

    return SimpleNamespace(link_update=link_update)
