"""Design-environment throughput: design steps per second over whole episodes, and body/metric throughput.

``python -m benchmarks env`` (or ``make bench``). A design step is one action in one environment; an episode of
N = 256 environments is T = 100 batched steps *plus* the end-of-episode work (largest component, the task's
reward, all body metrics), so the figure is what PPO's rollout sees. Actions are N(0, I), as from an untrained
policy. The paper's environment managed 1,991 design steps/s on a 2-core machine.

Wall-clock and process CPU time are both printed, with the load average: on a shared machine the wall-clock
figure is pessimistic, the CPU-time one is what the code costs.
"""

from __future__ import annotations

import os
import time

import torch

from freeform.body import bodies_and_metrics, largest_component
from freeform.envs import DesignEnv, EnvConfig

NUM_ENVS = 256
RESOLUTION = 20
STEPS = 100
EPISODES = 4


def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def design_steps_per_second(
    materials: int, device: torch.device, compute_metrics: bool = True
) -> tuple[float, float]:
    """(wall, cpu) design steps/s over EPISODES whole episodes (after one warm-up episode)."""
    env = DesignEnv(NUM_ENVS, EnvConfig(resolution=RESOLUTION, steps=STEPS),
                    materials=materials, device=device, compute_metrics=compute_metrics)
    g = torch.Generator(device=device).manual_seed(0)
    actions = torch.randn(EPISODES + 1, STEPS, NUM_ENVS, 3 + materials, generator=g, device=device)
    env.reset()
    for t in range(STEPS):
        env.step(actions[0, t])
    _sync(device)
    wall0, cpu0 = _clock()
    for e in range(1, EPISODES + 1):
        for t in range(STEPS):
            env.step(actions[e, t])
    _sync(device)
    wall1, cpu1 = _clock()
    steps = EPISODES * STEPS * NUM_ENVS
    return steps / (wall1 - wall0), steps / (cpu1 - cpu0)


def final_grids(materials: int, device: torch.device) -> torch.Tensor:
    env = DesignEnv(NUM_ENVS, EnvConfig(resolution=RESOLUTION, steps=STEPS),
                    materials=materials, device=device, compute_metrics=False)
    g = torch.Generator(device=device).manual_seed(1)
    env.reset()
    for _ in range(STEPS):
        _, _, _, info = env.step(torch.randn(NUM_ENVS, 3 + materials, generator=g, device=device))
    return info["final_grids"]


def grids_per_second(fn, grids: torch.Tensor, repeats: int = 5) -> tuple[float, float]:
    fn(grids)
    _sync(grids.device)
    wall0, cpu0 = _clock()
    for _ in range(repeats):
        fn(grids)
    _sync(grids.device)
    wall1, cpu1 = _clock()
    n = repeats * grids.shape[0]
    return n / (wall1 - wall0), n / (cpu1 - cpu0)


def snake_grids(n: int, rho: int, device: torch.device) -> torch.Tensor:
    """n copies of one 6-connected path through half the rows of a ρ³ grid (label propagation's worst case)."""
    grid = torch.zeros(rho, rho, rho, dtype=torch.uint8)
    rows = [
        (x, y)
        for x in range(0, rho, 2)
        for y in (range(0, rho, 2) if (x // 2) % 2 == 0 else range(rho - 2, -1, -2))
    ]
    for i, (x, y) in enumerate(rows):
        grid[x, y, :] = 1
        if i + 1 < len(rows):
            nx, ny = rows[i + 1]
            z = rho - 1 if i % 2 == 0 else 0
            grid[min(x, nx) : max(x, nx) + 1, min(y, ny) : max(y, ny) + 1, z] = 1
    return grid.expand(n, -1, -1, -1).contiguous().to(device)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> None:
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, load average {os.getloadavg()[0]:.1f}"
    )
    print(f"N = {NUM_ENVS}, ρ = {RESOLUTION}, T = {STEPS}; whole episodes incl. final body + metrics")
    for device in devices:
        for k in (2, 4):
            wall, cpu = design_steps_per_second(k, device)
            print(f"[{device.type}] design steps/s (k={k}): {wall:,.0f} wall, {cpu:,.0f} per CPU-second")
        wall, cpu = design_steps_per_second(4, device, compute_metrics=False)
        print(
            f"[{device.type}] design steps/s (k=4, body but no metrics): {wall:,.0f} wall, {cpu:,.0f} per CPU-second"
        )
        grids = final_grids(4, device)
        for name, fn in (
            ("largest_component", largest_component),
            ("bodies_and_metrics", bodies_and_metrics),
        ):
            wall, cpu = grids_per_second(fn, grids)
            print(
                f"[{device.type}] {name} on N(0,I) designs (k=4): {wall:,.0f} grids/s wall, {cpu:,.0f} per CPU-second"
            )
        snakes = snake_grids(NUM_ENVS, RESOLUTION, device)
        wall, cpu = grids_per_second(largest_component, snakes)
        print(
            f"[{device.type}] largest_component on snakes (2,099 voxels each): {wall:,.0f} grids/s wall, {cpu:,.0f} per CPU-second"
        )
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
