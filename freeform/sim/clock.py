"""The end of a step for one robot (spec sections 4, 10 and 12): its clock, status, rl4design's dynamic dt, the
step cap, the actuation phase of the next step and which snapshots that step takes.

Every robot has its own t, dt, step count and status: robots never interact, so a batch gives each robot exactly
its solo result, and one robot can stop (done, diverged, stalled) while the others go on.
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
import math
from types import SimpleNamespace

from freeform.sim.access import make_access
from freeform.sim.links import DT_REFRESH_STEPS
from freeform.sim.runtime import ti
from freeform.sim.state import DONE, EV_END, EV_SAMPLE, EV_START, GP, LR, RI, RT, RUNNING, STALLED

TWO_PI = 2 * math.pi


@functools.cache
def make_clock(precision: str, order: str) -> SimpleNamespace:
    """``robot_advance`` and ``set_phase`` for a precision and memory order."""
    acc = make_access(precision, order)
    ld, st = acc.ld, acc.st

    @ti.func
    def set_phase(r, s: ti.template(), tau):
        """sin and cos of 2π·τ/period: the actuation phase every voxel of robot r combines with its own φ."""
        a = TWO_PI * tau / ld(s.gp, GP.TEMP_PERIOD, 0)
        st(s.rt, RT.SIN, r, ti.sin(a))
        st(s.rt, RT.COS, r, ti.cos(a))

    @ti.func
    def actuation_time(r, s: ti.template()):
        """The time of the temperature robot r's voxels write in the coming step: t + dt (VX), t (rl4design, one
        step late)."""
        tau = ld(s.rt, RT.T, r) + ld(s.rt, RT.DT, r)
        if ti.static(s.sw.rl4design != 0):
            tau = ld(s.rt, RT.T, r)
        return tau

    @ti.func
    def max_link_omega2(r, s: ti.template()):
        """The largest ω² the robot's links stored this step (f64; 0 without links). A serial max in the robot
        phase: rl4design's dt refresh needs no float64 atomic (a compare-and-swap loop on CUDA)."""
        w = ti.cast(0.0, ti.f64)
        for lk in range(ld(s.ri, RI.LSTART, r), ld(s.ri, RI.LEND, r)):
            w = ti.max(w, ti.cast(ld(s.lr, LR.OMEGA2, lk), ti.f64))
        return w

    @ti.func
    def robot_advance(r, s: ti.template()):
        """End of a step for robot r. ``s.sw`` (``state.Switches``): rl4design semantics, its dynamic dt refresh."""
        st(s.rt, RT.DTPREV, r, ld(s.rt, RT.DT, r))
        st(s.rt, RT.T, r, ld(s.rt, RT.T, r) + ld(s.rt, RT.DT, r))  # (not `+=`: on global data that is an atomic add)
        step = ld(s.ri, RI.STEP, r) + 1
        st(s.ri, RI.STEP, r, step)
        if ld(s.rt, RT.T, r) > ld(s.gp, GP.T_END, 0) and ld(s.ri, RI.STATUS, r) == RUNNING:
            st(s.ri, RI.STATUS, r, DONE)
        if step >= ld(s.ri, RI.MAXSTEP, r) and ld(s.ri, RI.STATUS, r) == RUNNING:
            st(s.ri, RI.STATUS, r, STALLED)  # its dt collapsed: stop it rather than hold up the batch
        if ti.static(s.sw.dynamic_dt != 0):
            if step % DT_REFRESH_STEPS == 0:
                omega2 = max_link_omega2(r, s)
                if omega2 > 0.0:
                    st(s.rt, RT.DT, r, ld(s.gp, GP.DT_FRAC, 0) / (TWO_PI * ti.sqrt(omega2)))
        set_phase(r, s, actuation_time(r, s))
        # the next step's snapshots, with the same f64 clock arithmetic as Engine's for step 0
        t_before = ld(s.rt, RT.T, r)
        t_after = t_before + ld(s.rt, RT.DT, r)
        events = 0
        if (step + 1) % ld(s.ri, RI.PERIOD, r) == 0:
            events |= EV_SAMPLE
        if t_before <= ld(s.gp, GP.BURN_IN, 0) and t_after > ld(s.gp, GP.BURN_IN, 0):
            events |= EV_START
        if t_before <= ld(s.gp, GP.T_END, 0) and t_after > ld(s.gp, GP.T_END, 0):
            events |= EV_END
        st(s.ri, RI.EVENTS, r, events)

    return SimpleNamespace(robot_advance=robot_advance, set_phase=set_phase, actuation_time=actuation_time)
