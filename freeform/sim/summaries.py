"""The robots' trace samples, reduced on the device (``Simulator.simulate(trace_every=...)``).

A trace sample summarises each robot's voxels — mass-weighted sums for the centre of mass, the bounding box, how
many voxels touch the ground, the summed orientation — into one column of ``SUMMARY`` numbers. The schedules write
robot r's column of frame f into the trace region ``[frames, SUMMARY.width, robots]`` when the robot has run f × k
steps (k = the trace interval in steps), inside the stepping kernel: the host neither stops the batch at every
sample (each stop waits for the slowest robot) nor copies the voxel table (on a GPU, megabytes a sample).

One thread walks a robot's voxels in order: no float atomics, so the sums are the same on every run and either
schedule. The host finishes the samples (divides by the mass, normalises the orientation): ``Simulator``.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
from types import SimpleNamespace

from freeform.sim.access import make_access
from freeform.sim.runtime import ti
from freeform.sim.state import CONTACT, HDR, MT, RI, RT, SUMMARY, VI, VR


@functools.cache
def make_summaries(precision: str, order: str) -> SimpleNamespace:
    """``summarise_robot`` (a func: robot r's voxels as they are now into frame f of the trace region ``s.tr``) and
    the kernel ``summarise(reals, ints, f64s, frame)`` that writes every robot's. (Built here, not at import:
    importing freeform.sim chooses no backend.)"""
    acc = make_access(precision, order)
    ld, get3, get4, header, bind = acc.ld, acc.get3, acc.get4, acc.header, acc.bind
    Reals, Ints, F64s = acc.Buffer["reals"], acc.Buffer["ints"], acc.Buffer["f64s"]

    @ti.func
    def put(s: ti.template(), f, c: ti.template(), r, x):
        """Trace element ``[f, c, r]`` (the region is ``[frames, SUMMARY.width, robots]``, row-major)."""
        s.tr.buf[s.h[s.tr.at] + (f * SUMMARY.width + c) * s.h[s.tr.stride] + r] = x

    @ti.func
    def summarise_robot(r, s: ti.template(), f):
        mx = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        # the box starts at the first voxel (a robot has one), not at ±inf: fast-math assumes no infinities
        lo = ti.cast(get3(s.vr, VR.POS, ld(s.ri, RI.VSTART, r)), ti.f64)
        hi = lo
        q = ti.Vector([0.0, 0.0, 0.0, 0.0], dt=ti.f64)
        m = ti.cast(0.0, ti.f64)
        contacts = 0
        for v in range(ld(s.ri, RI.VSTART, r), ld(s.ri, RI.VEND, r)):
            mass = ti.cast(ld(s.mt, MT.MASS, ld(s.vi, VI.MAT, v)), ti.f64)
            p = ti.cast(get3(s.vr, VR.POS, v), ti.f64)
            mx += mass * p
            m += mass
            lo, hi = ti.min(lo, p), ti.max(hi, p)
            if (ld(s.vi, VI.FLAGS, v) & CONTACT) != 0:
                contacts += 1
            o = ti.cast(get4(s.vr, VR.ORI, v), ti.f64)
            q += -o if o[0] < 0.0 else o  # q and −q are one rotation: sum the ones with w ≥ 0
        put(s, f, SUMMARY.T, r, ld(s.rt, RT.T, r))
        put(s, f, SUMMARY.STATUS, r, ti.cast(ld(s.ri, RI.STATUS, r), ti.f64))
        put(s, f, SUMMARY.M, r, m)
        put(s, f, SUMMARY.CONTACTS, r, ti.cast(contacts, ti.f64))
        for k in ti.static(range(3)):
            put(s, f, SUMMARY.MX + k, r, mx[k])
            put(s, f, SUMMARY.LO + k, r, lo[k])
            put(s, f, SUMMARY.HI + k, r, hi[k])
        for k in ti.static(range(4)):
            put(s, f, SUMMARY.Q + k, r, q[k])

    @ti.kernel
    def summarise(reals: Reals, ints: Ints, f64s: F64s, frame: ti.i32):
        for r in range(ints[HDR.N_ROBOTS]):
            h = header(ints)
            summarise_robot(r, bind(reals, ints, f64s, h, None), frame)

    return SimpleNamespace(summarise_robot=summarise_robot, summarise=summarise)
