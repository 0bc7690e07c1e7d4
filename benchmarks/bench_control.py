"""Closed-loop control speed (freeform/envs/control.py): control steps per second of ``ControlEnv`` with N = 128
design bodies (≈ 76 voxels each, ρ = 20) for a control period of 1, 10 and 100 simulator steps (fixed dt), and
the time outside the simulator (writing the commands, sensing, the reward) as a share of the simulator's own time
(``Engine.advance_time`` alone, measured on the same bodies just before). Issue 29's goal: ≤ 20 % at the default
period (0.0125 s ≈ 100 steps at the default dt). Then the engine's own part of a control step, the same commands
and period two ways, alternated: ``set_commands`` + ``advance_time`` + ``sense`` (a call each, and the column
writes and clock reads between them) against ``Engine.control_step`` (one call to the device).

``python -m benchmarks control``; ``FREEFORM_BENCH_QUICK=1`` uses 32 bodies; ``FREEFORM_BENCH_SCHEDULE=robots`` (or
``native``) runs that schedule instead of the CPU's default (``sim.schedule``, docs/physics.md).
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from benchmarks.bench_sim import built_for, random_design_bodies
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.sim import SimConfig, Simulator

DT = 1e-4  # fixed, so that a period is a whole number of steps
SCHEDULE = os.environ.get("FREEFORM_BENCH_SCHEDULE", "auto")
EVERY = (1, 10, 100)
ROUNDS = {1: 40, 10: 20, 100: 6}


def measure(grids: torch.Tensor, every: int, rounds: int, device: str = "cpu") -> tuple[float, float, float, float]:
    """(control steps per second, simulator seconds per control step, seconds outside it, seconds of the env's own
    host work) of ``ControlEnv`` on ``grids`` with a period of ``every`` simulator steps (fixed dt), zero actions,
    after one step that compiles. "Outside" is a step less ``advance_time`` alone (so it counts writing the commands
    and sensing); the host work is a step less its ``Engine.control_step`` (the one call that writes the commands,
    runs the period and senses)."""
    n = grids.shape[0]
    control = ControlConfig(period=every * DT, duration=1000 * every * DT, burn_in=0.0)
    env = ControlEnv(grids, sim=SimConfig(dt=DT, schedule=SCHEDULE), control=control, device=device)
    env.reset()
    actions = torch.zeros((n, env.action_dim), device=device)
    env.step(actions)  # compile (or load the kernel cache) what a step runs, and what advance_time runs
    env.engine.advance_time(control.period)
    # (no explicit synchronisation: every call below ends by reading the robots' state back to the host)
    t0 = time.perf_counter()
    for _ in range(rounds):
        env.engine.advance_time(control.period)
    sim = (time.perf_counter() - t0) / rounds
    engine_time, control_step = [0.0], env.engine.control_step

    def timed(*args, **kwargs):
        t = time.perf_counter()
        out = control_step(*args, **kwargs)
        engine_time[0] += time.perf_counter() - t
        return out

    env.engine.control_step = timed
    t0 = time.perf_counter()
    for _ in range(rounds):
        env.step(actions)
    total = (time.perf_counter() - t0) / rounds
    del env.engine.control_step
    return 1 / total, sim, max(total - sim, 0.0), total - engine_time[0] / rounds


def measure_engine(grids: torch.Tensor, every: int, rounds: int, arch: str = "cpu") -> tuple[float, float]:
    """Seconds per control period of the engine alone on ``grids`` (f32, fixed dt, zero commands): stepwise
    (set_commands, advance_time, sense) and in one call (control_step), alternated round by round."""
    period = every * DT
    config = SimConfig(dt=DT, actuation="command", burn_in=0.0, duration=1000 * period, schedule=SCHEDULE)
    engines = []
    for _ in range(2):
        sim = Simulator(config, arch=arch)
        engines.append(sim.engine(sim.layout(grids)))  # (a Simulator each: each its own arrays)
    stepwise, one_call = engines
    zero = np.zeros(stepwise.layout.num_voxels)
    times = np.zeros(2)
    for k in range(rounds + 1):  # (the first round compiles)
        t0 = time.perf_counter()
        stepwise.set_commands(zero)
        stepwise.advance_time(period)
        stepwise.sense()
        t1 = time.perf_counter()
        one_call.control_step(zero, period)
        t2 = time.perf_counter()
        if k:
            times += (t1 - t0, t2 - t1)
    return tuple(times / rounds)


def main() -> None:
    n = 32 if os.environ.get("FREEFORM_BENCH_QUICK") else 128
    grids = random_design_bodies(n)
    print(f"{n} design bodies, {int((grids > 0).sum()) / n:.0f} voxels each on average, ρ = {grids.shape[1]}; "
          f"fixed dt = {DT} s; f32, CPU ({torch.get_num_threads()} torch threads), schedule {SCHEDULE}"
          f"{built_for(SCHEDULE)}")
    print(f"  {'period':>16s} {'control steps/s':>16s} {'sim ms/step':>12s} {'outside ms/step':>16s} {'outside/sim':>12s}"
          f" {'env host ms':>12s} {'host/sim':>9s}")
    for every in EVERY:
        rate, sim, outside, host = measure(grids, every, ROUNDS[every])
        print(f"  {every:>5d} steps ({every * DT * 1e3:.1f} ms) {rate:16.1f} {sim * 1e3:12.2f} "
              f"{outside * 1e3:16.2f} {outside / sim:11.0%} {host * 1e3:12.2f} {host / sim:8.0%}", flush=True)
    print("  the engine's part of a control step: set_commands + advance_time + sense, against control_step (one call)")
    print(f"  {'period':>16s} {'stepwise ms':>12s} {'one call ms':>12s} {'saved ms':>9s}")
    for every in EVERY:
        stepwise, one_call = measure_engine(grids, every, 2 * ROUNDS[every])
        print(f"  {every:>5d} steps ({every * DT * 1e3:.1f} ms) {stepwise * 1e3:12.2f} {one_call * 1e3:12.2f} "
              f"{(stepwise - one_call) * 1e3:9.2f}", flush=True)


if __name__ == "__main__":
    main()
