"""The robots' trace samples, reduced on the device (``Simulator.simulate(trace_every=...)``).

A trace sample summarises each robot's voxels — mass-weighted sums for the centre of mass, the bounding box, how
many voxels touch the ground, the summed orientation — into one column of ``SUMMARY`` numbers. The schedules write
robot r's column of frame f into the trace array ``[frames, SUMMARY.width, robots]`` when the robot has run f × k
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
from freeform.sim.state import CONTACT, MT, RI, RT, SUMMARY, VI, VR


@functools.cache
def make_summaries(precision: str, order: str) -> SimpleNamespace:
    """``summarise_robot`` (a func: robot r's voxels as they are now into frame f of a trace array), the kernel
    ``summarise(vr, vi, rt, ri, mt, n_robots, out, frame)`` that writes every robot's, and ``TraceArr``, the trace
    array's argument type (f64 ``[frames, SUMMARY.width, robots]``). (Built here, not at import: importing
    freeform.sim chooses no backend.)"""
    TraceArr = ti.types.ndarray(dtype=ti.f64, ndim=3)
    acc = make_access(precision, order)
    ld, get3, get4 = acc.ld, acc.get3, acc.get4

    @ti.func
    def summarise_robot(r, vr: ti.template(), vi: ti.template(), rt: ti.template(), ri: ti.template(),
                        mt: ti.template(), out: ti.template(), f):
        mx = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        # the box starts at the first voxel (a robot has one), not at ±inf: fast-math assumes no infinities
        lo = ti.cast(get3(vr, VR.POS, ld(ri, RI.VSTART, r)), ti.f64)
        hi = lo
        q = ti.Vector([0.0, 0.0, 0.0, 0.0], dt=ti.f64)
        m = ti.cast(0.0, ti.f64)
        contacts = 0
        for v in range(ld(ri, RI.VSTART, r), ld(ri, RI.VEND, r)):
            mass = ti.cast(ld(mt, MT.MASS, ld(vi, VI.MAT, v)), ti.f64)
            p = ti.cast(get3(vr, VR.POS, v), ti.f64)
            mx += mass * p
            m += mass
            lo, hi = ti.min(lo, p), ti.max(hi, p)
            if (ld(vi, VI.FLAGS, v) & CONTACT) != 0:
                contacts += 1
            o = ti.cast(get4(vr, VR.ORI, v), ti.f64)
            q += -o if o[0] < 0.0 else o  # q and −q are one rotation: sum the ones with w ≥ 0
        out[f, SUMMARY.T, r] = ld(rt, RT.T, r)
        out[f, SUMMARY.STATUS, r] = ti.cast(ld(ri, RI.STATUS, r), ti.f64)
        out[f, SUMMARY.M, r] = m
        out[f, SUMMARY.CONTACTS, r] = ti.cast(contacts, ti.f64)
        for k in ti.static(range(3)):
            out[f, SUMMARY.MX + k, r] = mx[k]
            out[f, SUMMARY.LO + k, r] = lo[k]
            out[f, SUMMARY.HI + k, r] = hi[k]
        for k in ti.static(range(4)):
            out[f, SUMMARY.Q + k, r] = q[k]

    @ti.kernel
    def summarise(vr: acc.arg(VR), vi: acc.arg(VI), rt: acc.arg(RT), ri: acc.arg(RI), mt: acc.arg(MT),
                  n_robots: ti.i32, out: TraceArr, frame: ti.i32):
        for r in range(n_robots):
            summarise_robot(r, vr, vi, rt, ri, mt, out, frame)

    return SimpleNamespace(summarise_robot=summarise_robot, summarise=summarise, TraceArr=TraceArr)
