"""PPO benchmarks: update throughput of the paper's locomotion network, and one volume-task epoch.

1. Update throughput — samples per second through PPO's SGD step (forward, loss, backward, Adam) with the paper's
   locomotion network (k = 4, h = 256, ρ = 20), minibatch 128, for the fast trunk and the plain ``nn.Conv3d``
   trunk, and the largest parameter difference between the two after the same updates.
2. Volume epoch — one PPO epoch on the volume task at 64 environments × T = 100, 4 SGD passes, minibatch 128
   (k = 2, h = 128): seconds sampling (of which in ``env.step``) and learning.

Reference on the 2-core development machine: RLlib 2.0.1 takes ≈ 38 s for that epoch (11 s sampling, 27 s
learning) and a plain Conv3d trunk trains at ≈ 800 samples/s. ``FREEFORM_BENCH_QUICK=1`` shortens both.
"""

from __future__ import annotations

import copy
import os
import time

import torch

from freeform.agents import PPO, PPOConfig, VoxelActorCritic
from freeform.envs import DesignEnv, EnvConfig, VolumeTask


def update_benchmark(repeats: int) -> dict[str, float]:
    """One SGD pass over a real rollout (16 envs × T = 100 of the untrained policy on DesignEnv, k = 4) with the
    locomotion network, for the fast and the plain trunk from the same state: samples/s (best of ``repeats`` for
    the fast one; a shared machine only ever adds time) and the parameters' largest difference afterwards."""
    env = DesignEnv(16, EnvConfig(resolution=20, steps=100), materials=4, compute_metrics=False)
    torch.manual_seed(0)
    policy = VoxelActorCritic(resolution=20, materials=4, hidden=256, trunk="fast")
    cfg = PPOConfig(rollout_steps=100, num_sgd_iter=1, sgd_minibatch_size=128, seed=0)
    ppo = PPO(env, policy, cfg)
    ppo.collect()  # design states: from empty to ≈ 80 filled voxels (1-4 % of the grid)
    start = copy.deepcopy(ppo.state_dict())
    samples = (ppo.rollout.rewards.numel() // cfg.sgd_minibatch_size) * cfg.sgd_minibatch_size
    out: dict[str, float] = {"occupancy": (ppo.rollout.obs > 0).float().mean().item()}
    params = {}
    for trunk, reps in (("fast", repeats), ("conv", 1)):
        policy.trunk = trunk  # same parameters, other computation
        best = float("inf")
        for _ in range(reps):
            ppo.load_state_dict(copy.deepcopy(start))
            t0 = time.perf_counter()
            ppo.update()
            best = min(best, time.perf_counter() - t0)
        out[trunk] = samples / best
        params[trunk] = [p.detach().clone() for p in policy.parameters()]
    out["max_param_diff"] = max((a - b).abs().max().item() for a, b in zip(params["fast"], params["conv"], strict=True))
    out["samples"] = samples
    return out


def volume_epoch(epochs: int) -> list[dict[str, float]]:
    """Stats of ``epochs`` volume-task epochs at 64 envs × T = 100, 4 SGD passes, minibatch 128."""
    torch.manual_seed(0)
    env = DesignEnv(64, EnvConfig(resolution=20, steps=100), materials=2, task=VolumeTask())
    cfg = PPOConfig(rollout_steps=100, num_sgd_iter=4, sgd_minibatch_size=128, seed=0)
    ppo = PPO(env, VoxelActorCritic(resolution=20, materials=2, hidden=128), cfg)
    return ppo.learn(epochs)


def main() -> None:
    quick = os.environ.get("FREEFORM_BENCH_QUICK") == "1"
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op threads, CPU "
          "(timings on a shared machine are pessimistic)")

    print("\n-- PPO update throughput: VoxelActorCritic(ρ=20, k=4, h=256), minibatch 128, one SGD pass --")
    r = update_benchmark(repeats=2 if quick else 5)
    print(f"rollout: {r['samples']:.0f} samples of real design states ({100 * r['occupancy']:.1f} % of voxels filled)")
    print(f"fast trunk (scatter + sparse CSR convs): {r['fast']:8.0f} samples/s")
    print(f"plain nn.Conv3d trunk:                   {r['conv']:8.0f} samples/s")
    print(f"speed-up: {r['fast'] / r['conv']:.1f}x; max |Δparam| after the same {r['samples'] // 128:.0f} Adam steps: "
          f"{r['max_param_diff']:.2e}")

    print("\n-- Volume-task epoch: 64 envs × T=100, 4 SGD passes, minibatch 128 (k=2, h=128) --")
    history = volume_epoch(1 if quick else 2)
    for i, s in enumerate(history):
        total = s["time_rollout"] + s["time_update"]
        print(f"epoch {i}: {total:6.2f} s = sampling {s['time_rollout']:.2f} s (env.step {s['time_env']:.2f} s) "
              f"+ learning {s['time_update']:.2f} s; {s['samples_per_second']:.0f} samples/s; "
              f"reward mean {s['episode_reward_mean']:.1f}")
    print("reference (RLlib 2.0.1, same machine): 38 s = 11 s sampling + 27 s learning")


if __name__ == "__main__":
    main()
