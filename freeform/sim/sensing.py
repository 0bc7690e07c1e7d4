"""What a controller senses, gathered on the device in one kernel (closed-loop control, ``freeform.envs.control``).

``sense(reals, ints, f64s, out)`` writes, for every voxel, a row of ``state.SENSE`` (its position relative to its
robot's centre of mass, its velocity, the mean |strain| of its links, ground contact), and after the voxels'
rows every robot's centre of mass: ``out`` f64 ``[n·SENSE.width + 3·R]``. One thread per robot sums its voxels in
order (as ``summaries.py``: no float atomics, the same sums on every run), then one thread per voxel.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
from types import SimpleNamespace

from freeform.sim.access import make_access
from freeform.sim.runtime import ti
from freeform.sim.state import CONTACT, HDR, LR, MT, RI, SENSE, VI, VR


@functools.cache
def make_sensing(precision: str, order: str) -> SimpleNamespace:
    """The ``sense`` kernel for a precision and memory order."""
    acc = make_access(precision, order)
    ld, get3, header, bind = acc.ld, acc.get3, acc.header, acc.bind
    Reals, Ints, F64s = acc.Buffer["reals"], acc.Buffer["ints"], acc.Buffer["f64s"]
    Out = ti.types.ndarray(dtype=ti.f64, ndim=1)

    @ti.func
    def centre_of_mass(r, s: ti.template(), out: ti.template(), at):
        mx = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        m = ti.cast(0.0, ti.f64)
        for v in range(ld(s.ri, RI.VSTART, r), ld(s.ri, RI.VEND, r)):
            mass = ti.cast(ld(s.mt, MT.MASS, ld(s.vi, VI.MAT, v)), ti.f64)
            mx += mass * ti.cast(get3(s.vr, VR.POS, v), ti.f64)
            m += mass
        for k in ti.static(range(3)):
            out[at + 3 * r + k] = mx[k] / m

    @ti.func
    def sense_voxel(v, s: ti.template(), out: ti.template(), at):
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
        row = v * SENSE.width
        for k in ti.static(range(3)):
            out[row + SENSE.REL + k] = p[k] - out[at + 3 * r + k]
            out[row + SENSE.VEL + k] = vel[k]
        out[row + SENSE.STRAIN] = strain / ti.max(links, 1)
        out[row + SENSE.CONTACT] = 1.0 if (ld(s.vi, VI.FLAGS, v) & CONTACT) != 0 else 0.0

    @ti.kernel
    def sense(reals: Reals, ints: Ints, f64s: F64s, out: Out):
        at = ints[HDR.N_VOXELS] * SENSE.width  # where the robots' centres of mass start
        for r in range(ints[HDR.N_ROBOTS]):
            h = header(ints)
            centre_of_mass(r, bind(reals, ints, f64s, h, None), out, at)
        for v in range(ints[HDR.N_VOXELS]):  # (after every robot's sum: the loops run in order)
            h = header(ints)
            sense_voxel(v, bind(reals, ints, f64s, h, None), out, at)

    return SimpleNamespace(sense=sense)
