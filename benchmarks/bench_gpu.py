"""The paper's epoch on a GPU, in parts: compile times, the simulator's µs per step by batch size, the epoch's
simulation, the update's ms per minibatch, closed-loop control steps per second (N = 128 and 1,024), and one
``paper_locomotion`` epoch split into environment, simulation and update (what ``scripts/gpu_check.sh`` runs; the goal: an epoch ≤ 2 s on one H100, ``docs/physics.md``).

``python -m benchmarks gpu`` on a CUDA machine; ``FREEFORM_BENCH_ARCH=cpu`` rehearses every figure on the CPU at a
small size (a few minutes on 2 cores; the sizes are printed with each figure).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from freeform.sim import SimConfig, Simulator, runtime

PAPER_SIM = dict(precision="f32", semantics="rl4design", burn_in=5.0, duration=5.0)  # the paper's protocol


def line(label: str, value: str) -> None:
    """One figure: its label padded to a column, then its value (every GPU benchmark's format)."""
    print(f"  {label:58s} {value}", flush=True)


def _bodies(n: int) -> torch.Tensor:
    from benchmarks.bench_sim import random_design_bodies

    return random_design_bodies(n, seed=0)


def sim_section(arch: str, rehearsal: bool) -> None:
    """Compile times (the first simulate of each configuration, and a graph's build), µs per step by batch."""
    print("simulator (flat schedule, design bodies of an untrained policy, f32, rl4design):")
    for launches in (0, SimConfig().graph_launches):
        cfg = SimConfig(**{**PAPER_SIM, "burn_in": 0.01, "duration": 0.01}, graph_launches=launches)
        t0 = time.perf_counter()
        Simulator(cfg, arch=arch, schedule="flat").simulate(_bodies(2))
        runtime.sync()
        what = "kernels (cold unless cached)" if not launches else f"+ a compute graph of {launches} launches"
        line(f"first simulate, {what}", f"{time.perf_counter() - t0:7.2f} s")
    steps = 128 if rehearsal else 512
    for batch in ((1, 8, 32) if rehearsal else (1, 32, 128, 512)):
        cells = []
        for launches in (0, SimConfig().graph_launches):
            cfg = SimConfig(**{**PAPER_SIM, "burn_in": 100.0}, graph_launches=launches)
            sim = Simulator(cfg, arch=arch, schedule="flat")
            engine = sim.engine(sim.layout(_bodies(batch)))
            engine.advance(steps)  # warm (and build the graph)
            runtime.sync()
            runs = []
            for _ in range(3):
                t0 = time.perf_counter()
                engine.advance(steps)
                runtime.sync()
                runs.append((time.perf_counter() - t0) / steps * 1e6)
            cells.append(f"{min(runs):7.1f}")
        line(f"µs per step, batch {batch}: launched from Python | compute graph", " | ".join(cells))
    batch, protocol = (16, {"burn_in": 0.25, "duration": 0.25}) if rehearsal else (128, {})
    cfg = SimConfig(**{**PAPER_SIM, **protocol})
    sim = Simulator(cfg, arch=arch, schedule="flat")
    t0 = time.perf_counter()
    r = sim.simulate(_bodies(batch))
    runtime.sync()
    line(f"the epoch's simulation: {batch} bodies, {cfg.burn_in:g} s + {cfg.duration:g} s "
         f"({int(r.steps.max())} steps)", f"{time.perf_counter() - t0:7.2f} s")


def update_section(device: str, rehearsal: bool) -> None:
    """The update alone: ms per minibatch of the paper's network (volume task: no simulation in the rollout), eager,
    ``torch.compile`` of the loss and the whole step as a CUDA graph (``agent.cuda_graph``)."""
    from freeform.config import compose
    from freeform.run.build import build

    # 4 passes of the paper's batch (128 × 100 samples: 400 minibatches) time a minibatch as well as its 50 do
    size = ["env.num_envs=16", "env.steps=20", "agent.num_sgd_iter=2"] if rehearsal else ["agent.num_sgd_iter=4"]
    # (on the CPU the paper network's sparse trunk branches on the data, which torch.compile recompiles for, and
    # there are no CUDA graphs: eager only)
    variants = (("eager", []),) if rehearsal else (
        ("eager", []), ("torch.compile", ["agent.compile=true"]), ("CUDA graph", ["agent.cuda_graph=true"]))
    for name, overrides in variants:
        try:
            cfg = compose("experiment=paper_volume", f"trainer.device={device}", "agent.cuda_graph=false", *size,
                          *overrides)
            _, ppo = build(cfg, torch.device(device))
            ppo.collect()
            first = time.perf_counter()
            ppo.update()
            first = time.perf_counter() - first
            runs = []
            for _ in range(2):
                ppo.collect()
                t0 = time.perf_counter()
                ppo.update()
                if device.startswith("cuda"):
                    torch.cuda.synchronize()
                runs.append(time.perf_counter() - t0)
        except Exception as e:  # one variant's failure is a figure too; the others still run
            line(f"update, {name}", f"FAILED: {type(e).__name__}: {str(e)[:200]}")
            continue
        batch = cfg.env.num_envs * cfg.env.steps
        minibatches = cfg.agent.num_sgd_iter * (batch // min(cfg.agent.sgd_minibatch_size, batch))
        line(f"update, {minibatches} minibatches of {cfg.agent.sgd_minibatch_size}, {name} (first update)",
             f"{statistics.median(runs) / minibatches * 1e3:7.2f} ms per minibatch ({first:.1f} s)")


def train_epochs(overrides: tuple[str, ...]) -> tuple[Any, dict[str, float], float]:
    """Train the composed config (``overrides``: a preset and its settings) in a scratch directory: the config,
    the last epoch's logged figures and the wall time of the whole call, compilation included."""
    from freeform.config import compose
    from freeform.run.trainer import train

    cfg = compose(*overrides)
    with tempfile.TemporaryDirectory() as run:
        t0 = time.perf_counter()
        history = train(cfg, Path(run)).history
        return cfg, history[-1], time.perf_counter() - t0


def epoch_section(device: str, rehearsal: bool) -> None:
    """One paper_locomotion epoch, as the trainer reports it (after a first epoch that compiles); on a GPU with the
    update as a CUDA graph (``agent.cuda_graph``) and eager."""
    preset = "experiment=locomotion_cpu" if rehearsal else "experiment=paper_locomotion"
    for update in (("agent.cuda_graph=false",) if rehearsal else ("agent.cuda_graph=true", "agent.cuda_graph=false")):
        try:
            cfg, last, wall = train_epochs((preset, f"trainer.device={device}", "trainer.epochs=2",
                                            "trainer.progress=false", "trainer.checkpoint_every=0", update))
        except Exception as e:
            line(f"{preset.split('=')[1]} epoch, {update}", f"FAILED: {type(e).__name__}: {str(e)[:200]}")
            continue
        rollout, upd = last.get("perf/time_rollout", float("nan")), last.get("perf/time_update", float("nan"))
        sim, env = last.get("perf/sim_seconds", float("nan")), last.get("perf/time_env", float("nan"))
        line(f"{preset.split('=')[1]} epoch 2 ({cfg.env.num_envs} robots, cuda_graph={cfg.agent.cuda_graph}): "
             "rollout (env | of it simulation) | update", f"{rollout:6.2f} s ({env:.2f} | {sim:.2f}) | {upd:6.2f} s")
        line("  both epochs, compilation included", f"{wall:7.1f} s")


def control_section(arch: str, device: str, rehearsal: bool) -> None:
    """Closed-loop control (issue 29): control steps per second of ControlEnv, a period of 100 simulator steps."""
    from benchmarks.bench_control import measure, measure_engine

    print("closed-loop control (ControlEnv, design bodies, f32, fixed dt 1e-4 s, a period of 100 steps):")
    for n in ((8, 16) if rehearsal else (128, 1024)):
        rate, sim, outside, host = measure(_bodies(n), 100, 3 if rehearsal else 10, device)
        line(f"{n} bodies: control steps/s | simulator ms | outside ms | env host ms a step",
             f"{rate:7.1f} | {sim * 1e3:7.2f} | {outside * 1e3:7.2f} | {host * 1e3:7.2f}")
        stepwise, one_call = measure_engine(_bodies(n), 100, 3 if rehearsal else 10, arch)
        line(f"{n} bodies: engine ms a period, stepwise (3 calls + steps) | one call (control_step)",
             f"{stepwise * 1e3:7.2f} | {one_call * 1e3:7.2f}")


def main() -> None:
    arch = runtime.ensure(os.environ.get("FREEFORM_BENCH_ARCH", "auto"))
    rehearsal = arch == "cpu"
    device = "cuda" if arch == "cuda" else "cpu"
    print(f"{runtime.describe()} on {arch}; torch {torch.__version__}"
          + (f" on {torch.cuda.get_device_name()}" if arch == "cuda" else " (CPU rehearsal: small sizes)"))
    sim_section(arch, rehearsal)
    update_section(device, rehearsal)
    control_section(arch, device, rehearsal)
    epoch_section(device, rehearsal)


if __name__ == "__main__":
    main()
