"""What a controller senses, gathered on the device (closed-loop control, ``freeform.envs.control``).

The sensing array ``out`` (f64 ``[n·SENSE.width + R·ROBOT_SENSE.width]``) holds, for every voxel, a row of
``state.SENSE`` (its position relative to its robot's centre of mass, its velocity, the mean |strain| of its links,
ground contact), then every robot's row of ``state.ROBOT_SENSE`` (its centre of mass, clock, dt and status). One
thread per robot sums its voxels in order (as ``summaries.py``: no float atomics, the same sums on every run), then
one thread per voxel. The funcs are shared by the ``sense`` kernel here and by the one-call
control step (``schedules.py``), which senses at the end of the same launch.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
from types import SimpleNamespace

from freeform.sim.access import make_access
from freeform.sim.runtime import ti
from freeform.sim.state import CONTACT, HDR, LR, MT, RI, ROBOT_SENSE, RT, SENSE, VI, VR


@functools.cache
def make_sensing(precision: str, order: str) -> SimpleNamespace:
    """The ``sense`` kernel for a precision and memory order, and its per-item funcs ``sense_robot(r, s, out)``
    and ``sense_voxel(v, s, out)`` (every robot's row before any voxel's: a voxel's row reads its robot's)."""
    acc = make_access(precision, order)
    ld, get3, header, bind = acc.ld, acc.get3, acc.header, acc.bind
    Reals, Ints, F64s = acc.Buffer["reals"], acc.Buffer["ints"], acc.Buffer["f64s"]
    Out = ti.types.ndarray(dtype=ti.f64, ndim=1)

    @ti.func
    def robot_row(s: ti.template(), r):
        """Where robot r's row starts: after every voxel's."""
        return s.h[HDR.N_VOXELS] * SENSE.width + r * ROBOT_SENSE.width

    @ti.func
    def sense_robot(r, s: ti.template(), out: ti.template()):
        mx = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        m = ti.cast(0.0, ti.f64)
        for v in range(ld(s.ri, RI.VSTART, r), ld(s.ri, RI.VEND, r)):
            mass = ti.cast(ld(s.mt, MT.MASS, ld(s.vi, VI.MAT, v)), ti.f64)
            mx += mass * ti.cast(get3(s.vr, VR.POS, v), ti.f64)
            m += mass
        row = robot_row(s, r)
        for k in ti.static(range(3)):
            out[row + ROBOT_SENSE.COM + k] = mx[k] / m
        out[row + ROBOT_SENSE.T] = ld(s.rt, RT.T, r)
        out[row + ROBOT_SENSE.DT] = ld(s.rt, RT.DT, r)
        out[row + ROBOT_SENSE.STATUS] = ti.cast(ld(s.ri, RI.STATUS, r), ti.f64)

    @ti.func
    def sense_voxel(v, s: ti.template(), out: ti.template()):
        r = ld(s.vi, VI.ROBOT, v)
        mat = ld(s.vi, VI.MAT, v)
        p = ti.cast(get3(s.vr, VR.POS, v), ti.f64)
        vel = ti.cast(get3(s.vr, VR.MOM, v) * ld(s.mt, MT.MINV, mat), ti.f64)
        strain, links = ti.cast(0.0, ti.f64), 0
        for d in ti.static(range(6)):
            lk = ld(s.vi, VI.SLOT + d, v)
            if lk >= 0:
                strain += ti.abs(ti.cast(ld(s.lr, LR.STRAIN, lk), ti.f64))
                links += 1
        row, com = v * SENSE.width, robot_row(s, r) + ROBOT_SENSE.COM
        for k in ti.static(range(3)):
            out[row + SENSE.REL + k] = p[k] - out[com + k]
            out[row + SENSE.VEL + k] = vel[k]
        out[row + SENSE.STRAIN] = strain / ti.max(links, 1)
        out[row + SENSE.CONTACT] = 1.0 if (ld(s.vi, VI.FLAGS, v) & CONTACT) != 0 else 0.0

    @ti.kernel
    def sense(reals: Reals, ints: Ints, f64s: F64s, out: Out):
        for r in range(ints[HDR.N_ROBOTS]):
            h = header(ints)
            sense_robot(r, bind(reals, ints, f64s, h, None), out)
        for v in range(ints[HDR.N_VOXELS]):  # (after every robot's row: the loops run in order)
            h = header(ints)
            sense_voxel(v, bind(reals, ints, f64s, h, None), out)

    return SimpleNamespace(sense=sense, sense_robot=sense_robot, sense_voxel=sense_voxel, Out=Out)
