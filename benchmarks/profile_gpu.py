"""Where a GPU epoch's remaining time goes: the CUDA kernels of one eager minibatch step of the paper's network
(torch.profiler, the top kernels by GPU time; a CUDA graph replays the same kernels) and the host functions of one
closed-loop control step at N = 1,024 bodies (cProfile). Diagnostics for the GPU issue, not a benchmark:

    python -m benchmarks.profile_gpu        # on a CUDA machine (scripts/gpu_check.sh's wheels)
"""

from __future__ import annotations

import cProfile
import io
import pstats

import torch


def update_kernels() -> None:
    from freeform.config import compose
    from freeform.run.build import build

    cfg = compose("experiment=paper_volume", "trainer.device=cuda", "agent.num_sgd_iter=1", "agent.cuda_graph=false")
    _, ppo = build(cfg, torch.device("cuda"))
    ppo.collect()
    ppo.update()  # warm
    ppo.collect()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA,
                                            torch.profiler.ProfilerActivity.CPU]) as prof:
        ppo.update()
        torch.cuda.synchronize()
    print("one update of 100 minibatches of 128, eager: top CUDA kernels")
    print(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=14, max_name_column_width=60))


def control_host(n: int = 1024) -> None:
    from benchmarks.bench_control import DT
    from benchmarks.bench_sim import random_design_bodies
    from freeform.envs.control import ControlConfig, ControlEnv
    from freeform.sim import SimConfig

    control = ControlConfig(period=100 * DT, duration=1000 * 100 * DT, burn_in=0.0)
    env = ControlEnv(random_design_bodies(n), sim=SimConfig(dt=DT), control=control, device="cuda")
    env.reset()
    actions = torch.zeros((n, env.action_dim), device="cuda")
    env.step(actions)
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(5):
        env.step(actions)
    prof.disable()
    out = io.StringIO()
    pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(16)
    print(f"5 control steps at N = {n}, by own time:")
    print("\n".join(line[:150] for line in out.getvalue().splitlines()[:45]))


if __name__ == "__main__":
    from freeform.sim import runtime

    runtime.ensure("cuda")
    update_kernels()
    control_host()
