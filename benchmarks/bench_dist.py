"""Data-parallel PPO throughput: the same volume-task run with 1 and 2 CPU processes (``gloo``).

Both runs are spawned the same way (``torch.multiprocessing``, one intra-op thread per process) with the CPU demo's
sizes (``experiment=volume_cpu``: 64 environments × T = 30, ρ = 12, k = 2, h = 128, minibatch 256) and 4 SGD
passes. Reported per process count: samples per second over whole epochs (rollout + update; best of the timed
epochs, a shared machine only adds time), the rollout and update seconds, and the cost of one gradient all-reduce
(the 162,752-parameter flat buffer). 2 processes on a 2-core machine can at best halve the time; every minibatch
step pays one all-reduce. No GPU figures: none was available (``docs/scaling.md``).

``FREEFORM_BENCH_QUICK=1`` times one epoch instead of three.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

NUM_ENVS, RHO, STEPS, SGD_ITERS, MINIBATCH, HIDDEN = 64, 12, 30, 4, 256, 128


def _worker(rank: int, world: int, init_file: str, out_dir: str, epochs: int) -> None:
    torch.set_num_threads(1)
    if world > 1:
        dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    from freeform.agents import PPO, PPOConfig, VoxelActorCritic
    from freeform.agents.distributed import env_slice
    from freeform.envs import DesignEnv, EnvConfig, VolumeTask

    lo, hi = env_slice(NUM_ENVS, world, rank)
    torch.manual_seed(0)
    env = DesignEnv(hi - lo, EnvConfig(resolution=RHO, steps=STEPS), materials=2, task=VolumeTask())
    policy = VoxelActorCritic(resolution=RHO, materials=2, hidden=HIDDEN)
    cfg = PPOConfig(rollout_steps=STEPS, num_sgd_iter=SGD_ITERS, sgd_minibatch_size=MINIBATCH, seed=0, lr=1e-3)
    ppo = PPO(env, policy, cfg)
    ppo.train_epoch()  # warm-up: caches, allocator
    rows = []
    for _ in range(epochs):
        if world > 1:
            dist.barrier()
        t0 = time.perf_counter()
        stats = ppo.train_epoch()
        rows.append((time.perf_counter() - t0, stats["time_rollout"], stats["time_update"]))
    allreduce = float("nan")
    if world > 1:
        buffer = torch.randn(sum(p.numel() for p in policy.parameters()))
        dist.barrier()
        t0 = time.perf_counter()
        for _ in range(50):
            dist.all_reduce(buffer)
        allreduce = (time.perf_counter() - t0) / 50
        dist.barrier()
        dist.destroy_process_group()
    if rank == 0:
        torch.save({"rows": rows, "allreduce": allreduce}, Path(out_dir) / f"world{world}.pt")
    os._exit(0)  # skip native teardown (see tests/test_distributed.py)


def run(world: int, epochs: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        mp.spawn(_worker, args=(world, str(Path(tmp) / "pg"), tmp, epochs), nprocs=world, join=True)
        result = torch.load(Path(tmp) / f"world{world}.pt", weights_only=False)
    best = min(result["rows"], key=lambda r: r[0])
    samples = NUM_ENVS * STEPS
    return {
        "samples_per_second": samples / best[0],
        "epoch_s": best[0],
        "rollout_s": best[1],
        "update_s": best[2],
        "allreduce_ms": 1e3 * result["allreduce"],
    }


def main() -> None:
    epochs = 1 if os.environ.get("FREEFORM_BENCH_QUICK") else 3
    print(
        f"volume task, {NUM_ENVS} envs x T={STEPS}, rho={RHO}, k=2, h={HIDDEN}, {SGD_ITERS} SGD passes x minibatch "
        f"{MINIBATCH} ({(NUM_ENVS * STEPS // MINIBATCH) * SGD_ITERS} steps/epoch); best of {epochs} epoch(s), "
        "1 thread per process, gloo"
    )
    base = None
    for world in (1, 2):
        r = run(world, epochs)
        base = base or r["samples_per_second"]
        extra = f", all-reduce of the gradients {r['allreduce_ms']:.2f} ms" if world > 1 else ""
        print(
            f"  {world} process(es): {r['samples_per_second']:7.0f} samples/s (x{r['samples_per_second'] / base:.2f}), "
            f"epoch {r['epoch_s']:.2f} s = rollout {r['rollout_s']:.2f} s + update {r['update_s']:.2f} s{extra}",
            flush=True,
        )


if __name__ == "__main__":
    main()
