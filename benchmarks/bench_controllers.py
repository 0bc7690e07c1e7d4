"""The controllers' cost on the CPU (freeform/agents/networks/controllers.py): each kind of ``CONTROLLERS`` at its presets'
width, for 64 bodies of two settings — the design setting (64 untrained designs of ρ = 8, 4 materials, 20 design
steps: ``experiment=locomotion_cpu``'s; their union box) and the walker (``benchmarks/data/walker.npy``: the body a
``lab.control`` run of ``control_locomotion_cpu`` trained on, ``control.bodies=walker``; 64 copies: one small box) — timing

* the forward pass per control step (``no_grad``, the 64 bodies' observation: what acting costs a rollout step),
* the update's step: forward + backward on a minibatch of 512 samples (the 64 observations 8 times over).

The fastest of repeated runs (the machine is shared: the kinds are timed in turn, round after round, and the
minimum is the least disturbed), after a warm-up; one thread (``FREEFORM_BENCH_THREADS`` sets another count: with two
threads on the shared 2-core machine, a busy neighbour made every op ten times slower). ``python -m benchmarks controllers``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch

from freeform.agents.networks.controllers import CONTROLLERS, build_controller, controller_step
from freeform.agents.networks.recurrent import RecurrentPolicy
from freeform.envs.control import ControlConfig, ControlEnv

WALKER = Path(__file__).resolve().parent / "data" / "walker.npy"
ROUNDS = 5
WIDTHS = {"conv": 16, "mlp": 64, "context": 16, "attention": 32, "context_gru": 16, "attention_gru": 32,
          "attention_hyper": 32}
SEQUENCE = 8  # a recurrent controller's update runs the 512 samples as 64 sequences of 8 steps (one stroke episode)


def seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def settings() -> dict[str, torch.Tensor]:
    from freeform.evolve import untrained_design_bodies

    designs = untrained_design_bodies(80, 8, 4, 20, 2, 0)
    designs = designs[(designs.flatten(1) > 0).any(dim=1)][:64]
    walker = torch.from_numpy(np.load(WALKER)).expand(64, -1, -1, -1).clone()
    return {"design ρ=8": designs, "walker": walker}


def main() -> None:
    threads = int(os.environ.get("FREEFORM_BENCH_THREADS", "1"))
    torch.set_num_threads(threads)
    print(f"threads {threads}")
    print("| setting | box | voxels (mean) | kind | width | parameters | forward, 64 bodies (ms) | update step, 512 "
          "samples (ms) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, grids in settings().items():
        env = ControlEnv(grids, control=ControlConfig(burn_in=0.0, duration=0.05))
        obs = env.reset()
        batch = obs.repeat(8, 1, 1, 1, 1)
        voxels = float(obs[:, env.filled_channel].flatten(1).sum(1).mean())
        nets, forward, update = {}, {}, {}
        for kind in CONTROLLERS:
            torch.manual_seed(0)
            nets[kind] = build_controller(kind, env, WIDTHS[kind])
            forward[kind], update[kind] = [], []
        for round in range(ROUNDS + 1):
            for kind, net in nets.items():
                def act(net=net, obs=obs) -> None:
                    with torch.no_grad():
                        controller_step(net, obs)

                def learn(net=net, batch=batch) -> None:
                    if isinstance(net, RecurrentPolicy):
                        seq = batch.view(SEQUENCE, -1, *batch.shape[1:])
                        start = torch.zeros(seq.shape[:2], dtype=torch.bool)
                        mean, log_std, _, value, _ = net(seq, net.initial_state(seq.shape[1]), start)
                    else:
                        mean, log_std, _, value = net(batch)
                    (mean.square().mean() + log_std.mean() + value.square().mean()).backward()
                    net.zero_grad(set_to_none=True)

                f = min(seconds(act) for _ in range(5))
                u = seconds(learn)
                if round:  # (round 0: the warm-up)
                    forward[kind].append(f)
                    update[kind].append(u)
        for kind, net in nets.items():
            params = sum(p.numel() for p in net.parameters())
            print(f"| {name} | {'×'.join(map(str, env.box))} | {voxels:.0f} | {kind} | {WIDTHS[kind]} | {params:,} | "
                  f"{1e3 * min(forward[kind]):.2f} | {1e3 * min(update[kind]):.0f} |", flush=True)

if __name__ == "__main__":
    main()
