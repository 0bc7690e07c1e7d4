"""Simulator throughput in voxel-steps per second (voxels × steps / wall time, kernels compiled beforehand).

Figures: a batch of 128 bodies designed by N(0, I) actions (k = 4, ρ = 20, T = 100, largest component); a batch
of 10³ cubes; throughput against batch size (1..512 random bodies) and against body size (5³, 10³, 20³ cubes).
Voxelyze does 2.2-3.0 M voxel-steps/s on one core of the reference machine (spec section 15).

``python -m benchmarks sim`` (env ``FREEFORM_BENCH_PRECISION=f64`` to measure double precision).
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from freeform.sim import SimConfig, Simulator

RHO, K, T_ACTIONS = 20, 4, 100
TARGET_VOXEL_STEPS = 1.5e7  # per measurement: long enough to dwarf launch overhead, short enough for ~2 min total


def random_design_bodies(n: int, seed: int = 0) -> torch.Tensor:
    """Bodies of an untrained policy: uint8 ``[n, ρ, ρ, ρ]`` (largest 6-connected component of the final grid)."""
    try:  # the project's own environment, once it has landed
        from freeform.body import largest_component  # type: ignore[attr-defined]
        from freeform.envs import DesignEnv  # type: ignore[attr-defined]

        env = DesignEnv(num_envs=n, resolution=RHO, num_materials=K, episode_length=T_ACTIONS)
        env.reset(seed=seed)
        gen = torch.Generator().manual_seed(seed)
        for _ in range(T_ACTIONS):
            env.step(torch.randn(n, 3 + K, generator=gen))
        return largest_component(env.grids)
    except Exception:
        return _design_bodies_fallback(n, seed)


def _design_bodies_fallback(n: int, seed: int) -> torch.Tensor:
    """design.md's action -> bundle rule and largest component, written out (numpy + scipy)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    grids = np.zeros((n, RHO, RHO, RHO), dtype=np.uint8)
    for _ in range(T_ACTIONS):
        a = rng.standard_normal((n, 3 + K))
        f = 0.5 + np.clip(a, -2, 2) / 4
        hi = np.ceil(RHO * f[:, :3]).astype(int)
        mat = np.argmax(f[:, 3:], axis=1).astype(np.uint8)  # ties -> lowest index
        for e in range(n):
            sl = tuple(slice(max(h - 1, 0), min(h + 1, RHO)) for h in hi[e])
            grids[e][sl] = mat[e]
    structure = ndimage.generate_binary_structure(3, 1)
    out = np.zeros_like(grids)
    for e in range(n):
        lab, count = ndimage.label(grids[e] > 0, structure=structure)
        if count:
            sizes = np.bincount(lab.ravel())[1:]
            keep = 1 + int(np.argmax(sizes))  # ties -> first component in C order
            out[e] = np.where(lab == keep, grids[e], 0)
    return torch.from_numpy(out)


def throughput(sim: Simulator, grids: torch.Tensor) -> tuple[float, float, int, int]:
    """(voxel-steps per wall second, per CPU second, voxels, steps) for one simulate() of ``grids``.

    The run is sized to ~TARGET_VOXEL_STEPS. Per CPU second (all of this process's threads) is what the
    engine does on an uncontended core; on a shared machine the wall-clock figure mostly measures the others.
    """
    n_vox = int((grids > 0).sum())
    steps = max(200, int(TARGET_VOXEL_STEPS / max(n_vox, 1)))
    dt = 1.1785e-4
    cfg = SimConfig(**{**sim.config.__dict__, "dt": dt, "burn_in": 0.0, "duration": (steps - 0.5) * dt})
    runner = Simulator(cfg, arch=sim.arch, schedule=sim.schedule)
    t0, c0 = time.perf_counter(), time.process_time()
    r = runner.simulate(grids)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    done = int(r.steps.max())
    return n_vox * done / wall, n_vox * done / cpu, n_vox, done


def main() -> None:
    precision = os.environ.get("FREEFORM_BENCH_PRECISION", "f32")
    sim = Simulator(SimConfig(precision=precision), arch="auto")
    cubes = lambda b, n: torch.ones((b, n, n, n), dtype=torch.uint8) * 2  # noqa: E731
    bodies = random_design_bodies(512, seed=0)
    throughput(sim, bodies[:2])  # compile (or load from the offline cache) outside the timings
    print(f"precision {precision}; {os.cpu_count()} CPU cores (shared machine: figures are pessimistic)")
    print(f"load average {os.getloadavg()[0]:.1f}; M voxel-steps/s per wall second | per CPU second")
    rate, crate, nv, st = throughput(sim, bodies[:128])
    print(f"128 N(0,I) design bodies ({nv} voxels, mean {nv / 128:.1f}/body), {st} steps: "
          f"{rate / 1e6:.2f} | {crate / 1e6:.2f}")
    rate, crate, nv, st = throughput(sim, cubes(32, 10))
    print(f"32 muscle cubes of 10^3 ({nv} voxels), {st} steps: {rate / 1e6:.2f} | {crate / 1e6:.2f}")
    print("batch size sweep (design bodies):")
    for b in (1, 8, 32, 128, 512):
        rate, crate, nv, st = throughput(sim, bodies[:b])
        print(f"  B={b:4d}  voxels={nv:6d}  steps={st:6d}  {rate / 1e6:6.2f} | {crate / 1e6:6.2f}")
    print("body size sweep (16 passive cubes):")
    for n in (5, 10, 20):
        rate, crate, nv, st = throughput(sim, cubes(16, n) // 2)
        print(f"  {n:2d}^3  voxels={nv:6d}  steps={st:6d}  {rate / 1e6:6.2f} | {crate / 1e6:6.2f}")


if __name__ == "__main__":
    main()
