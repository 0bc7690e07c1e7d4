"""Simulator throughput in voxel-steps per second (voxels × steps / time; kernels compiled beforehand).

Figures: a batch of 128 bodies designed by N(0, I) actions through the real ``DesignEnv`` (k = 4 materials,
ρ = 20, T = 100 actions, b = 2; the body is the largest component, ``info["bodies"]`` at the last step); a batch of
muscle cubes of 10³; throughput against batch size (1 … 512 design bodies) and against body size (5³, 10³, 20³);
the 128 design bodies on rough ground, stairs and a slope against flat ground (kernels only, alternated).
Voxelyze does 2.2-3.0 M voxel-steps/s on one core of the reference machine (spec section 15).

Every figure is given twice: per wall-clock second (what a user waits) and per CPU second of this process
(``time.process_time``, all threads) — on a shared machine the wall figure mostly measures the other tenants,
while the CPU-second figure is what the engine does with the core time it actually receives.

``python -m benchmarks sim``; environment: ``FREEFORM_BENCH_PRECISION=f64`` measures double precision,
``FREEFORM_BENCH_SCALE=0.2`` shortens every run (a quick look; launch overheads then weigh more).
"""

from __future__ import annotations

import os
import time

import torch

from freeform.envs.design import DesignEnv
from freeform.sim import SimConfig, Simulator, Terrain

RHO, K, T_ACTIONS, BUNDLE = 20, 4, 100, 2  # the paper's locomotion design setting (design.md)
DT = 1.1785e-4  # the recommended step of the paper's materials × 0.95 (every robot with links gets this)
# voxel-steps per measurement: long enough to dwarf launch and layout overheads, short enough for ~2 min in all
TARGET_VOXEL_STEPS = 3.5e7 * float(os.environ.get("FREEFORM_BENCH_SCALE", "1"))


def random_design_bodies(n: int, seed: int = 0) -> torch.Tensor:
    """Bodies of an untrained policy: uint8 ``[n, ρ, ρ, ρ]``, the largest 6-connected component of each grid that
    ``DesignEnv`` builds from T actions drawn from N(0, I) (no fallback: if the environment breaks, this does)."""
    env = DesignEnv(n, resolution=RHO, materials=K, steps=T_ACTIONS, bundle_size=BUNDLE, seed=seed,
                    compute_metrics=False)
    env.reset(seed=seed)
    gen = torch.Generator().manual_seed(seed)
    info: dict = {}
    for _ in range(T_ACTIONS):
        _, _, done, info = env.step(torch.randn(n, env.action_dim, generator=gen))
    if not bool(done.all()) or "bodies" not in info:
        raise RuntimeError("DesignEnv did not end its episode after T actions with info['bodies']")
    return info["bodies"]


def cubes(batch: int, edge: int, material: int) -> torch.Tensor:
    """``batch`` solid cubes of ``edge``³ voxels of one material: uint8 ``[batch, edge, edge, edge]``."""
    return torch.full((batch, edge, edge, edge), material, dtype=torch.uint8)


def throughput(sim: Simulator, grids: torch.Tensor) -> tuple[float, float, int, int]:
    """(voxel-steps per wall second, per CPU second, voxels, steps) of one ``simulate(grids)``.

    The run is sized to ~TARGET_VOXEL_STEPS with a fixed dt (every robot takes the same number of steps); the
    clock covers the whole ``simulate`` call (layout, upload, kernels, result), as a task sees it.
    """
    n_vox = int((grids > 0).sum())
    steps = max(200, int(TARGET_VOXEL_STEPS / max(n_vox, 1)))
    cfg = SimConfig(**{**sim.config.__dict__, "dt": DT, "burn_in": 0.0, "duration": (steps - 0.5) * DT})
    runner = Simulator(cfg, arch=sim.arch, schedule=sim.schedule)
    t0, c0 = time.perf_counter(), time.process_time()
    r = runner.simulate(grids)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    done = int(r.steps.max())
    if int(r.steps.min()) != done or bool(r.diverged.any()):
        raise RuntimeError(f"benchmark run went wrong: steps {int(r.steps.min())}..{done}, "
                           f"{int(r.diverged.sum())} diverged")
    return n_vox * done / wall, n_vox * done / cpu, n_vox, done


def engine_throughput(sim: Simulator, grids: torch.Tensor, steps: int) -> tuple[float, float]:
    """(per wall second, per CPU second) of ``Engine.advance`` alone: the kernels, without layout, upload and
    results — the figure to hold against Voxelyze's own per-core step rate."""
    from freeform.sim import runtime

    cfg = SimConfig(**{**sim.config.__dict__, "dt": DT, "burn_in": 0.0, "duration": 1e9})
    eng = Simulator(cfg, arch=sim.arch, schedule=sim.schedule).engine(sim.layout(grids))
    eng.advance(10)
    runtime.sync()
    t0, c0 = time.perf_counter(), time.process_time()
    eng.advance(steps)
    runtime.sync()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    n = eng.layout.num_voxels * steps
    return n / wall, n / cpu


def terrain_comparison(sim: Simulator, design: torch.Tensor, rounds: int = 3) -> dict[str, float]:
    """Kernels-only M voxel-steps per CPU second of ``design`` on each terrain (the best of ``rounds`` alternated
    runs, so that every terrain sees the same machine load); printed with the cost relative to flat ground."""
    terrains = {"flat": Terrain.flat(), "rough (3 mm, 4 cm)": Terrain.rough(0.003, 0.04),
                "stairs (3 mm, 2 cm)": Terrain.steps(0.003, 0.02), "slope 5 deg": Terrain.slope(5)}
    nv = int((design > 0).sum())
    steps = max(200, int(TARGET_VOXEL_STEPS / nv / rounds))
    best = dict.fromkeys(terrains, 0.0)
    for _ in range(rounds):
        for name, terrain in terrains.items():
            tsim = Simulator(SimConfig(**{**sim.config.__dict__, "terrain": terrain}), arch=sim.arch,
                             schedule=sim.schedule)
            best[name] = max(best[name], engine_throughput(tsim, design, steps)[1] / 1e6)
    for name, rate in best.items():
        print(f"  {name:<34s} {rate:6.2f} per CPU-s  ({100 * (best['flat'] / rate - 1):+5.1f} % time vs flat)",
              flush=True)
    return best


def main() -> None:
    precision = os.environ.get("FREEFORM_BENCH_PRECISION", "f32")
    sim = Simulator(SimConfig(precision=precision), arch="auto")
    bodies = random_design_bodies(512, seed=0)
    throughput(sim, bodies[:2])  # compile (or load from the offline cache) outside the timings
    from freeform.sim import runtime

    print(f"precision {precision}; arch {runtime.ensure('auto')}, {runtime.num_threads()} Taichi threads on "
          f"{os.cpu_count()} CPU cores; load average {os.getloadavg()[0]:.1f} at the start")
    print("M voxel-steps/s: per wall second | per CPU second (wall is pessimistic on a shared machine)")

    def row(label: str, grids: torch.Tensor) -> None:
        rate, crate, nv, st = throughput(sim, grids)
        print(f"  {label:<34s} voxels={nv:6d} steps={st:5d}  {rate / 1e6:6.2f} | {crate / 1e6:6.2f}", flush=True)

    design = bodies[:128]
    nv = int((design > 0).sum())
    row(f"128 N(0,I) design bodies ({nv / 128:.1f}/body)", design)
    rate, crate = engine_throughput(sim, design, max(200, int(TARGET_VOXEL_STEPS / nv)))
    print(f"  {'  the same, kernels only':<34s} {'':27s}{rate / 1e6:6.2f} | {crate / 1e6:6.2f}", flush=True)
    row("32 muscle cubes 10^3", cubes(32, 10, 2))
    print(f"terrain ({design.shape[0]} design bodies, kernels only, best of 3 alternated runs):")
    terrain_comparison(sim, design)
    print("batch size (N(0,I) design bodies):")
    for b in (1, 8, 32, 128, 512):
        row(f"B={b}", bodies[:b])
    print("body size (passive cubes):")
    for n, b in ((5, 64), (10, 16), (20, 4)):
        row(f"{b} cubes {n}^3", cubes(b, n, 1))
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
