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

import os
import time

import torch

from freeform.agents import PPO, PPOConfig, VoxelActorCritic
from freeform.envs import DesignEnv, VolumeTask


def _fill_random_rollout(ppo: PPO, seed: int) -> None:
    """Random grids with ~30 % filled voxels, random actions/returns: the update's cost does not depend on them."""
    g = torch.Generator().manual_seed(seed)
    ro = ppo.rollout
    k = ppo.env.materials
    filled = torch.rand(ro.obs.shape, generator=g) < 0.3
    ro.obs.copy_(torch.where(filled, torch.randint(1, k, ro.obs.shape, generator=g), 0).to(torch.uint8))
    ro.actions.copy_(torch.randn(ro.actions.shape, generator=g))
    with torch.no_grad():
        flat = ro.obs.reshape(-1, *ro.obs.shape[2:])
        mean, log_std, value = ppo.policy(flat)
    ro.means.copy_(mean.reshape(ro.means.shape))
    ro.log_stds.copy_(log_std.reshape(ro.log_stds.shape))
    ro.values.copy_(value.reshape(ro.values.shape))
    ro.logprobs.copy_(-0.5 * ((ro.actions - ro.means) / ro.log_stds.exp()).square().sum(-1) - ro.log_stds.sum(-1))
    ro.returns = torch.rand(ro.returns.shape, generator=g) * 100
    ro.advantages = ro.returns - ro.values


def update_throughput(trunk: str, batch: int, seed: int = 0) -> tuple[float, PPO]:
    """Samples/s of ``PPO.update`` (one pass over ``batch`` samples) for the locomotion network with ``trunk``."""
    env = DesignEnv(num_envs=batch // 4, resolution=20, materials=4, steps=100, compute_metrics=False)
    torch.manual_seed(seed)
    policy = VoxelActorCritic(resolution=20, materials=4, hidden=256, trunk=trunk)
    cfg = PPOConfig(rollout_steps=4, num_sgd_iter=1, sgd_minibatch_size=128, seed=seed)
    ppo = PPO(env, policy, cfg)
    _fill_random_rollout(ppo, seed)
    start = time.perf_counter()
    ppo.update()
    return batch / (time.perf_counter() - start), ppo


def volume_epoch(epochs: int) -> list[dict[str, float]]:
    """Stats of ``epochs`` volume-task epochs at 64 envs × T = 100, 4 SGD passes, minibatch 128."""
    torch.manual_seed(0)
    env = DesignEnv(num_envs=64, resolution=20, materials=2, steps=100, task=VolumeTask())
    cfg = PPOConfig(rollout_steps=100, num_sgd_iter=4, sgd_minibatch_size=128, seed=0)
    ppo = PPO(env, VoxelActorCritic(resolution=20, materials=2, hidden=128), cfg)
    return ppo.learn(epochs)


def main() -> None:
    quick = os.environ.get("FREEFORM_BENCH_QUICK") == "1"
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op threads, CPU "
          "(timings on a shared machine are pessimistic)")

    print("\n-- PPO update throughput: VoxelActorCritic(ρ=20, k=4, h=256), minibatch 128, one pass --")
    fast_batch, conv_batch = (1280, 256) if quick else (6400, 1280)
    update_throughput("fast", 256)  # warm-up: builds the sparse structures, touches the allocator
    fast_sps, fast_ppo = update_throughput("fast", fast_batch)
    conv_sps, conv_ppo = update_throughput("conv", conv_batch)
    print(f"fast trunk (sparse CSR convs): {fast_sps:8.0f} samples/s  ({fast_batch} samples)")
    print(f"plain nn.Conv3d trunk:         {conv_sps:8.0f} samples/s  ({conv_batch} samples)")
    print(f"speed-up: {fast_sps / conv_sps:.1f}x")
    # Same init, same minibatches: after identical updates the two trunks' parameters agree to float rounding.
    _, a = update_throughput("fast", 256, seed=1)
    _, b = update_throughput("conv", 256, seed=1)
    diff = max((p - q).abs().max().item() for p, q in zip(a.policy.parameters(), b.policy.parameters(), strict=True))
    print(f"max |Δparam| fast vs plain after 2 identical Adam steps: {diff:.2e}")

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
