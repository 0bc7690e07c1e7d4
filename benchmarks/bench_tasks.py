"""What a CPU demo epoch's scoring costs per task: the 64 untrained designs of one epoch (8³, T = 20, k = 4),
simulated for the demos' 2 s burn-in + 0.5 s evaluation, scored by ``locomotion`` (no trace), the ``rough`` reward on
flat and on rough ground (20 ms trace), and ``jump`` with its 5 ms trace and with a 20 ms one. Two repeats each,
interleaved (a shared machine drifts); seconds per call. ``FREEFORM_BENCH_QUICK=1``: 16 designs, one repeat.
"""

from __future__ import annotations

import os
import time

import torch

from freeform.envs import DesignEnv, LocomotionTask
from freeform.envs.trajectory import TrajectoryTask
from freeform.evolve import design_grids
from freeform.sim import SimConfig, Terrain


def main() -> None:
    quick = os.environ.get("FREEFORM_BENCH_QUICK") == "1"
    n, repeats = (16, 1) if quick else (64, 2)
    env = DesignEnv(n, resolution=8, materials=4, steps=20, compute_metrics=False)
    grids = design_grids(env, torch.randn((n, env.steps, env.action_dim), generator=torch.Generator().manual_seed(0)))
    flat = SimConfig(burn_in=2.0, duration=0.5)
    rough = SimConfig(burn_in=2.0, duration=0.5, terrain=Terrain.rough(0.003, 0.04))
    tasks = {
        "locomotion (no trace)": LocomotionTask(sim=flat, arch="cpu"),
        "rough reward, flat ground, 20 ms trace": TrajectoryTask("rough", sim=flat, trace_every=0.02, arch="cpu"),
        "rough reward, rough ground, 20 ms trace": TrajectoryTask("rough", sim=rough, trace_every=0.02, arch="cpu"),
        "jump, 20 ms trace": TrajectoryTask("jump", sim=flat, trace_every=0.02, arch="cpu"),
        "jump, 5 ms trace (its config)": TrajectoryTask("jump", sim=flat, trace_every=0.005, arch="cpu"),
    }
    for task in tasks.values():
        task.reward(grids[:2])  # Taichi compiles its kernels on the first call
    seconds: dict[str, list[float]] = {name: [] for name in tasks}
    for _ in range(repeats):
        for name, task in tasks.items():
            t0 = time.perf_counter()
            task.reward(grids)
            seconds[name].append(time.perf_counter() - t0)
    print(f"| task, {n} untrained designs, 2 s + 0.5 s | seconds per scoring ({repeats} repeats) |")
    print("|---|---|")
    for name, s in seconds.items():
        print(f"| {name} | {', '.join(f'{x:.2f}' for x in s)} |")


if __name__ == "__main__":
    main()
