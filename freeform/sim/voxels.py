"""The voxel update (spec sections 6-9, ``CVX_Voxel::timeStep``): Poisson strain, forces, floor contact and friction,
symplectic Euler with the quaternion update, then the rest size for the next step's actuation (spec section 4).

A voxel gathers the forces of its ≤ 6 links from the links' own columns through its fixed slots (``VI.SLOT``).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
from types import SimpleNamespace

from freeform.sim.access import make_access, make_numbers
from freeform.sim.clock import make_clock
from freeform.sim.config import POISSON_SERIES_TERMS
from freeform.sim.quat import make_quat
from freeform.sim.runtime import ti
from freeform.sim.state import (
    CONTACT,
    DIVERGED,
    EV_END,
    EV_SAMPLE,
    EV_START,
    FIXED,
    GP,
    LI,
    LR,
    LT,
    MT,
    NO_LIMIT,
    RI,
    RT,
    STATIC,
    VI,
    VR,
)
from freeform.sim.terrain import FLAT, SMOOTH

RENORM_NEWTON = 1e-4  # f32 renormalisation: |1 − |q|²| below this uses one Newton step (error < 1e-8)
POISSON_SERIES_X = 0.1  # |Σ tension strains| below which f32 uses the binomial series (config.POISSON_SERIES_TERMS)


@functools.cache
def make_voxels(precision: str, order: str) -> SimpleNamespace:
    """``voxel_update`` (and the actuation's ``temperature``/``base_size``) for a precision and memory order."""
    num = make_numbers(precision)
    acc = make_access(precision, order)
    q = make_quat(precision)
    real, vec3, vec4, exact_vx, nonfinite = num.real, num.vec3, num.vec4, num.exact_vx, num.nonfinite
    ld, st, get3, set3, get4, set4 = acc.ld, acc.st, acc.get3, acc.set3, acc.get4, acc.set4
    qmul, rotate, from_rotation_vector = q.qmul, q.rotate, q.from_rotation_vector
    actuation_time = make_clock(precision, order).actuation_time

    # ------------------------------------------------------------ actuation (spec section 4)
    @ti.func
    def base_size(s: ti.template(), mat, temp):
        """Rest size of a voxel along any axis: L·(1 + T·CTE) (extScale = 1)."""
        return ld(s.mt, MT.L, mat) * (1.0 + temp * ld(s.mt, MT.CTE, mat))

    @ti.func
    def temperature(s: ti.template(), v, mat, r):
        """T(τ) = T_base + A·sin(2π(τ/period + φ)), φ in cycles; sin/cos of 2πτ/period come from the robot. Under
        commanded actuation (``s.sw.command`` 1) the voxel's command takes the sine's place; under residual
        actuation (2) it corrects the sine, the sum kept in the sine's range (a zero command leaves the sine's
        bits: |sine| ≤ 1)."""
        wave = ti.cast(0.0, real)
        command = ti.cast(0.0, real)
        if ti.static(s.sw.command != 0):
            command = ld(s.vr, VR.CMD, v)
            ramp, until = ld(s.rt, RT.RAMP, r), ld(s.rt, RT.UNTIL, r)
            if ramp > 0.0 and until < NO_LIMIT:  # a ramp from CMD0, ending at the control period's end
                frac = 1.0 - (until - actuation_time(r, s)) / ramp
                if frac < 1.0:
                    before = ld(s.vr, VR.CMD0, v)
                    command = before + (command - before) * ti.cast(ti.max(frac, 0.0), real)
        if ti.static(s.sw.command == 1):
            wave = command
        else:
            wave = ti.cast(ld(s.rt, RT.SIN, r), real) * ld(s.mt, MT.COSPHI, mat) + \
                ti.cast(ld(s.rt, RT.COS, r), real) * ld(s.mt, MT.SINPHI, mat)
            if ti.static(s.sw.command == 2):
                wave = ti.min(ti.max(wave + command, -1.0), 1.0)
        return ld(s.vr, VR.TBASE, v) + ti.cast(ld(s.gp, GP.TEMP_AMP, 0), real) * wave

    # ------------------------------------------------------------ Poisson effects (spec section 6)
    @ti.func
    def poisson_strain(v, s: ti.template(), mat, nu):
        """This voxel's strain along each axis from its links' strains of this step (VX ``strain(true)``).

        An axis with links on both sides is in tension and keeps its mean link strain; a free axis takes
        (1 + Σ tension strains)^(−ν) − 1. Cached for the next link update: VX computes it lazily at the next
        step's first link, and nothing has changed by then (a Jacobi update)."""
        strain = vec3(0.0, 0.0, 0.0)
        if nu != 0.0:
            tension = ti.Vector([0, 0, 0])
            for a in ti.static(range(3)):
                cnt = 0
                for side in ti.static(range(2)):
                    lk = ld(s.vi, VI.SLOT + 2 * a + side, v)
                    if lk >= 0:
                        eps = ld(s.lr, LR.STRAIN, lk)
                        if ti.static(side == 1):  # a NEG slot: this voxel is the link's positive end
                            strain[a] += eps * ld(s.lt, LT.PSPOS, ld(s.li, LI.LMAT, lk))
                        else:
                            strain[a] += eps * ld(s.lt, LT.PSNEG, ld(s.li, LI.LMAT, lk))
                        cnt += 1
                if cnt == 2:
                    strain[a] *= 0.5
                    tension[a] = 1
            if not (tension[0] == 1 and tension[1] == 1 and tension[2] == 1):
                add = ti.cast(0.0, real)
                for a in ti.static(range(3)):
                    if tension[a] == 1:
                        add += strain[a]
                val = ti.cast(0.0, real)
                if ti.static(exact_vx):
                    val = ti.pow(1.0 + add, -nu) - 1.0
                else:
                    # f32: the binomial series where it converges fast (|x| < 0.1: truncation < 3e-9 relative, 20×
                    # below f32 rounding), else powf. Cheaper than the libm call (~10 % of a CPU step on design
                    # bodies, mostly surface voxels) and no 1 − 1 cancellation.
                    if ti.abs(add) < POISSON_SERIES_X:
                        c = ld(s.mt, MT.PB1 + POISSON_SERIES_TERMS - 1, mat)
                        for k in ti.static(range(POISSON_SERIES_TERMS - 1, 0, -1)):
                            c = ld(s.mt, MT.PB1 + k - 1, mat) + add * c
                        val = add * c
                    else:
                        val = ti.pow(1.0 + add, -nu) - 1.0
                for a in ti.static(range(3)):
                    if tension[a] == 0:
                        strain[a] = val
        return strain


    @ti.func
    def transverse(s: ti.template(), mat, ps):
        """Transverse areas and strain sums (VX_Voxel.cpp) for a link along x, y, z from the voxel's Poisson
        strains ``ps``: two vec3, computed once per voxel per step rather than by each of its ≤ 6 links."""
        L = ld(s.mt, MT.L, mat)
        area = vec3(L * L, L * L, L * L)
        ssum = vec3(0.0, 0.0, 0.0)
        if ld(s.mt, MT.NU, mat) != 0.0:
            area = vec3(L * L * (1.0 + ps[1]) * (1.0 + ps[2]), L * L * (1.0 + ps[0]) * (1.0 + ps[2]),
                        L * L * (1.0 + ps[0]) * (1.0 + ps[1]))
            ssum = vec3(ps[1] + ps[2], ps[0] + ps[2], ps[0] + ps[1])
        return area, ssum

    # ------------------------------------------------------------ forces (spec sections 7 and 8)
    @ti.func
    def link_loads(v, s: ti.template()):
        """Sum of the force and moment of the voxel's links, in its local frame (VX_Voxel::force/moment)."""
        force = vec3(0.0, 0.0, 0.0)
        moment = vec3(0.0, 0.0, 0.0)
        for d in ti.static(range(6)):
            lk = ld(s.vi, VI.SLOT + d, v)
            if lk >= 0:
                if ti.static(d % 2 == 1):  # NEG slot: this voxel is the link's positive end
                    force += get3(s.lr, LR.FP, lk)
                    moment += get3(s.lr, LR.MP, lk)
                else:
                    force += get3(s.lr, LR.FN, lk)
                    moment += get3(s.lr, LR.MN, lk)
        return force, moment

    @ti.func
    def floor_force(s: ti.template(), mat, force, vel, pen, static):
        """Floor contact at penetration ``pen`` (the start of the step) and Coulomb friction with the static/kinetic
        states (VX_Voxel::floorForce). Returns (force with contact, the kinetic friction part, static)."""
        fric = vec3(0.0, 0.0, 0.0)
        if pen >= 0.0:
            normal = ld(s.mt, MT.KPEN, mat) * pen
            force[2] += normal - ld(s.mt, MT.CC, mat) * vel[2]  # collision damping only while in contact
            if static:
                mus = ld(s.mt, MT.MUS, mat) * normal
                if force[0] * force[0] + force[1] * force[1] > mus * mus:
                    static = False  # breaks loose; the full force acts this step
            else:
                vh = ti.sqrt(vel[0] * vel[0] + vel[1] * vel[1])
                if vh > 0.0:
                    f = ld(s.mt, MT.MUK, mat) * normal / vh
                    fric = vec3(-f * vel[0], -f * vel[1], 0.0)
                    force += fric
        else:
            static = False
        return force, fric, static

    # ------------------------------------------------------------ terrain (terrain.py): distance and normal
    @ti.func
    def ground(s: ti.template(), p, mode: ti.template()):
        """Signed distance from point ``p`` to the terrain's surface (positive above) and the unit normal there.

        SMOOTH: S = base + gx·x + gy·y + the bilinear grid; distance (z − S)·n_z (exact for a plane).
        COLUMNS: flat-topped cells; the nearest of the own cell's top and the three nearest neighbours that rise
        above it (their top, edge or side: a voxel meets a riser on its face). Cells are at least a voxel wide,
        so no farther cell is within a voxel's half size."""
        c = ti.cast(ld(s.gp, GP.TER_CELL, 0), real)
        nx, ny = ti.cast(ld(s.gp, GP.TER_NX, 0), ti.i32), ti.cast(ld(s.gp, GP.TER_NY, 0), ti.i32)
        x0, y0 = ti.cast(ld(s.gp, GP.TER_X0, 0), real), ti.cast(ld(s.gp, GP.TER_Y0, 0), real)
        base = ti.cast(ld(s.gp, GP.TER_BASE, 0), real)
        # bounded before the integer conversion (a diverging robot's position must not overflow it)
        u = ti.min(ti.max((p[0] - x0) / c, -2.0), ti.cast(nx, real) + 2.0)
        v = ti.min(ti.max((p[1] - y0) / c, -2.0), ti.cast(ny, real) + 2.0)
        dist = ti.cast(0.0, real)
        n = vec3(0.0, 0.0, 1.0)
        if ti.static(mode == SMOOTH):
            gx, gy = ti.cast(ld(s.gp, GP.TER_GX, 0), real), ti.cast(ld(s.gp, GP.TER_GY, 0), real)
            i = ti.min(ti.max(ti.cast(ti.floor(u), ti.i32), 0), nx - 2)
            j = ti.min(ti.max(ti.cast(ti.floor(v), ti.i32), 0), ny - 2)
            fu, fv = u - ti.cast(i, real), v - ti.cast(j, real)
            inu = ti.cast(0.0 <= fu <= 1.0, real)  # beyond the grid the edge values go on: no grid slope there
            inv = ti.cast(0.0 <= fv <= 1.0, real)
            fu, fv = ti.min(ti.max(fu, 0.0), 1.0), ti.min(ti.max(fv, 0.0), 1.0)
            h00, h10 = ld(s.hf, 0, i * ny + j), ld(s.hf, 0, (i + 1) * ny + j)
            h01, h11 = ld(s.hf, 0, i * ny + j + 1), ld(s.hf, 0, (i + 1) * ny + j + 1)
            surface = base + gx * p[0] + gy * p[1] + (h00 * (1.0 - fu) + h10 * fu) * (1.0 - fv) + \
                (h01 * (1.0 - fu) + h11 * fu) * fv
            sx = gx + inu * ((h10 - h00) * (1.0 - fv) + (h11 - h01) * fv) / c
            sy = gy + inv * ((h01 - h00) * (1.0 - fu) + (h11 - h10) * fu) / c
            nz = 1.0 / ti.sqrt(1.0 + sx * sx + sy * sy)
            n = vec3(-sx * nz, -sy * nz, nz)
            dist = (p[2] - surface) * nz
        else:
            fi, fj = ti.floor(u), ti.floor(v)
            i, j = ti.cast(fi, ti.i32), ti.cast(fj, ti.i32)
            top0 = base + ld(s.hf, 0, ti.min(ti.max(i, 0), nx - 1) * ny + ti.min(ti.max(j, 0), ny - 1))
            dist = p[2] - top0
            si = 1 if u - fi >= 0.5 else -1
            sj = 1 if v - fj >= 0.5 else -1
            for k in ti.static(range(3)):
                a = i + (si if k != 1 else 0)
                b = j + (sj if k != 0 else 0)
                top = base + ld(s.hf, 0, ti.min(ti.max(a, 0), nx - 1) * ny + ti.min(ti.max(b, 0), ny - 1))
                if top > top0:
                    lox, loy = x0 + ti.cast(a, real) * c, y0 + ti.cast(b, real) * c
                    d = p - vec3(ti.min(ti.max(p[0], lox), lox + c), ti.min(ti.max(p[1], loy), loy + c),
                                 ti.min(p[2], top))
                    dl = ti.sqrt(d.dot(d))
                    if dl < dist:
                        dist = dl
                        if dl > 0.0:
                            n = d / dl
        return dist, n

    @ti.func
    def terrain_contact(s: ti.template(), mat, force, vel, pen, n, static):
        """``floor_force`` along the surface normal ``n``: penalty force and collision damping along n, Coulomb
        friction on the tangential force (static test) and velocity (kinetic). Returns (force, friction, static)."""
        fric = vec3(0.0, 0.0, 0.0)
        if pen >= 0.0:
            normal = ld(s.mt, MT.KPEN, mat) * pen
            force += (normal - ld(s.mt, MT.CC, mat) * vel.dot(n)) * n
            if static:
                mus = ld(s.mt, MT.MUS, mat) * normal
                fn = force.dot(n)
                if force.dot(force) - fn * fn > mus * mus:
                    static = False  # breaks loose; the full force acts this step
            else:
                vt = vel - vel.dot(n) * n
                vh = ti.sqrt(vt.dot(vt))
                if vh > 0.0:
                    fric = -(ld(s.mt, MT.MUK, mat) * normal / vh) * vt
                    force += fric
        else:
            static = False
        return force, fric, static

    @ti.func
    def renormalise(q):
        """f32 keeps orientations unit (spec section 14): |q|² = 1 + e with e at rounding level (the update rotation
        is unit), so one Newton step of 1/√ from 1, (3 − |q|²)/2, is exact to O(e²); the sqrt and division stay
        for anything further off."""
        n2 = q.dot(q)
        r = q
        if ti.abs(n2 - 1.0) < RENORM_NEWTON:
            r = q * (1.5 - 0.5 * n2)
        else:
            r = q * (1.0 / ti.sqrt(n2))
        return r

    @ti.func
    def snapshots(v, s: ti.template(), r, pos):
        """COM samples every PERIOD steps; the evaluation start/end at the first step past each time (which of
        these this step takes was decided once for the robot, by the clock or the Engine)."""
        events = ld(s.ri, RI.EVENTS, r)
        if events != 0:
            if (events & EV_SAMPLE) != 0:
                set3(s.vr, VR.PSAMP, v, pos)
            if (events & EV_START) != 0:
                set3(s.vr, VR.PSTART, v, pos)
                set3(s.vr, VR.PCS, v, get3(s.vr, VR.PSAMP, v))
            if (events & EV_END) != 0:
                set3(s.vr, VR.PEND, v, pos)
                set3(s.vr, VR.PCE, v, get3(s.vr, VR.PSAMP, v))

    # ------------------------------------------------------------ contact: the step's translation with the ground
    @ti.func
    def flat_floor_step(s: ti.template(), mat, size, pos, mom, force, vel, dt, minv, static):
        """Voxelyze's flat floor, its own code (results bit for bit those of the simulator before terrain): the floor
        force and friction, the momentum and position update, and the stop test. -> (pos, mom, static, touching)."""
        touching = False
        pen = 0.5 * size - 0.5 * ld(s.mt, MT.L, mat) - pos[2]
        fric = vec3(0.0, 0.0, 0.0)
        if ti.static(s.sw.floor != 0):
            force, fric, static = floor_force(s, mat, force, vel, pen, static)
        mom += force * dt
        delta = mom * (dt * minv)
        if ti.static(s.sw.floor != 0):
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
        return pos, mom, static, touching

    @ti.func
    def terrain_step(s: ti.template(), mat, size, pos, mom, force, vel, dt, minv, static):
        """The same model along the terrain's local surface normal n ("horizontal" becomes tangential).
        -> (pos, mom, static, touching)."""
        touching = False
        dist, n = ground(s, pos, s.sw.terrain)
        pen = 0.5 * size - dist
        fric = vec3(0.0, 0.0, 0.0)
        if ti.static(s.sw.floor != 0):
            force, fric, static = terrain_contact(s, mat, force, vel, pen, n, static)
        mom += force * dt
        delta = mom * (dt * minv)
        if ti.static(s.sw.floor != 0):
            touching = pen >= 0.0
        if touching:
            work = fric.dot(delta)
            mn = mom.dot(n)
            mt_ = mom - mn * n
            hke = 0.5 * mt_.dot(mt_) * minv
            if hke + work <= 0.0:
                static = True
            if static:
                mom = mn * n
                delta = delta.dot(n) * n
        else:
            static = False
        pos += delta
        return pos, mom, static, touching

    @ti.func
    def rl4design_spin(s: ti.template(), mat, size, pos, static, amom):
        """rl4design zeroes the spin of a voxel in static contact with the ground (at its new position).
        -> amom."""
        if ti.static(s.sw.terrain == FLAT):
            if static and 0.5 * size - 0.5 * ld(s.mt, MT.L, mat) - pos[2] >= 0.0:
                amom = vec3(0.0, 0.0, 0.0)  # rl4design zeroes spin in static floor contact
        elif static:  # (the distance only matters for a static voxel: skip the terrain lookup else)
            dist_new, _n = ground(s, pos, s.sw.terrain)
            if 0.5 * size - dist_new >= 0.0:
                amom = vec3(0.0, 0.0, 0.0)
        return amom

    @ti.func
    def store_pose(v, s: ti.template(), r, pos, mom, q, amom):
        """Voxel ``v``'s new pose written back; its robot ``r`` marked DIVERGED if the pose is not finite."""
        # NaN or inf anywhere makes the L1 norm non-finite, and so does a finite state beyond the float range
        if nonfinite(ti.abs(pos[0]) + ti.abs(pos[1]) + ti.abs(pos[2]) + ti.abs(amom[0]) + ti.abs(amom[1])
                     + ti.abs(amom[2])):
            st(s.ri, RI.STATUS, r, DIVERGED)

        set3(s.vr, VR.POS, v, pos)
        set3(s.vr, VR.MOM, v, mom)
        set4(s.vr, VR.ORI, v, q)
        set3(s.vr, VR.AMOM, v, amom)

    # ------------------------------------------------------------ the voxel update (spec section 9)
    @ti.func
    def voxel_update(v, s: ti.template()):
        """One step of voxel ``v``; marks its robot DIVERGED if its pose becomes non-finite.
        ``s.sw`` (``state.Switches``, compile-time): floor contact on; terrain: FLAT (Voxelyze's own floor code) |
        SMOOTH | COLUMNS (the height field in ``s.gp``/``s.hf``); rl4design semantics."""
        r = ld(s.vi, VI.ROBOT, v)
        mat = ld(s.vi, VI.MAT, v)
        flags = ld(s.vi, VI.FLAGS, v)
        dt = ti.cast(ld(s.rt, RT.DT, r), real)
        minv, iinv = ld(s.mt, MT.MINV, mat), ld(s.mt, MT.IINV, mat)
        pos = get3(s.vr, VR.POS, v)
        mom = get3(s.vr, VR.MOM, v)
        q = get4(s.vr, VR.ORI, v)
        amom = get3(s.vr, VR.AMOM, v)
        size = ld(s.vr, VR.SIZE, v)  # the rest size at the start of the step
        ps = poisson_strain(v, s, mat, ld(s.mt, MT.NU, mat))

        if (flags & FIXED) != 0:
            # held in all 6 DOF (VX isFixedAll): back to the original pose, no motion
            pos = get3(s.vr, VR.POS0, v)
            mom = vec3(0.0, 0.0, 0.0)
            amom = vec3(0.0, 0.0, 0.0)
            q = vec4(1.0, 0.0, 0.0, 0.0)
        else:
            force, moment = link_loads(v, s)
            vel = mom * minv
            # global damping acts on the absolute velocity (VX's "slow" damping)
            force = rotate(q, force) - ld(s.mt, MT.CG, mat) * vel
            force[2] += ld(s.mt, MT.MG, mat)
            moment = rotate(q, moment) - ld(s.mt, MT.CGR, mat) * (amom * iinv)

            static = (flags & STATIC) != 0
            touching = False
            if ti.static(s.sw.terrain == FLAT):
                pos, mom, static, touching = flat_floor_step(s, mat, size, pos, mom, force, vel, dt, minv, static)
            else:
                pos, mom, static, touching = terrain_step(s, mat, size, pos, mom, force, vel, dt, minv, static)
            amom += moment * dt
            q = qmul(from_rotation_vector(amom * (dt * iinv)), q)
            if ti.static(not exact_vx):
                q = renormalise(q)
            if ti.static(s.sw.rl4design != 0 and s.sw.floor != 0):
                amom = rl4design_spin(s, mat, size, pos, static, amom)
            flags = (flags & ~(STATIC | CONTACT)) | (STATIC if static else 0) | (CONTACT if touching else 0)

        store_pose(v, s, r, pos, mom, q, amom)
        area, ssum = transverse(s, mat, ps)
        set3(s.vr, VR.TAREA, v, area)
        set3(s.vr, VR.TSUM, v, ssum)
        st(s.vi, VI.FLAGS, v, flags)
        # temperature for the next step: VX sets T(t) before each step; rl4design writes T(t) after the
        # voxel update, so its links lag one step behind (the robot's SIN/COS hold the right τ for each)
        st(s.vr, VR.SIZE, v, base_size(s, mat, temperature(s, v, mat, r)))
        snapshots(v, s, r, pos)

    return SimpleNamespace(voxel_update=voxel_update, base_size=base_size, temperature=temperature)
