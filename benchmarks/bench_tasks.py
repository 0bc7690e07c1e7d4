"""What a CPU demo epoch's scoring costs per task: one epoch's 64 untrained designs (the demos' 8³ grid, T = 20,
k = 4) scored by the task of each demo preset, composed from ``conf/experiment/<task>_cpu.yaml`` (the presets'
2 s burn-in + 0.5 s evaluation, ground and trace interval: nothing restated here), and the ``rough`` preset once
more on flat ground, which isolates what the rough ground costs. Two repeats each, interleaved (a shared machine
drifts); seconds per call. ``FREEFORM_BENCH_QUICK=1``: 16 designs, one repeat.
"""

from __future__ import annotations

import os
import time

import torch

from freeform.config import compose
from freeform.envs import DesignEnv, EnvConfig
from freeform.evolve import untrained_design_grids
from freeform.train import build_task

PRESETS = {
    "locomotion_cpu (no trace)": ("experiment=locomotion_cpu",),
    "rough_cpu (rough ground, 20 ms trace)": ("experiment=rough_cpu",),
    "rough_cpu on flat ground": ("experiment=rough_cpu", "sim.terrain.kind=flat"),
    "jump_cpu (5 ms trace)": ("experiment=jump_cpu",),
    "climb_cpu (slope)": ("experiment=climb_cpu",),
    "stairs_cpu": ("experiment=stairs_cpu",),
    "tallest_cpu": ("experiment=tallest_cpu",),
    "directional_cpu": ("experiment=directional_cpu",),
}


def main() -> None:
    quick = os.environ.get("FREEFORM_BENCH_QUICK") == "1"
    n, repeats = (16, 1) if quick else (64, 2)
    cpu = torch.device("cpu")
    configs = {name: compose(*overrides, "trainer.device=cpu") for name, overrides in PRESETS.items()}
    demo = configs["locomotion_cpu (no trace)"]
    env = DesignEnv(n, EnvConfig(resolution=demo.env.resolution, steps=demo.env.steps),
                    materials=demo.task.materials, compute_metrics=False)
    grids = untrained_design_grids(env, seed=0)
    tasks = {name: build_task(cfg, cpu) for name, cfg in configs.items()}
    for task in tasks.values():
        task.reward(grids[:2])  # Taichi compiles its kernels on the first call
    seconds: dict[str, list[float]] = {name: [] for name in tasks}
    for _ in range(repeats):
        for name, task in tasks.items():
            t0 = time.perf_counter()
            task.reward(grids)
            seconds[name].append(time.perf_counter() - t0)
    print(f"| demo preset's task, {n} untrained designs | seconds per scoring ({repeats} repeats) |")
    print("|---|---|")
    for name, s in seconds.items():
        print(f"| {name} | {', '.join(f'{x:.2f}' for x in s)} |")


if __name__ == "__main__":
    main()
