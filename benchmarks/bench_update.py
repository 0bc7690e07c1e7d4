"""The design update on a GPU, trunk by trunk (issue 44: the update's share of the paper's epoch).

The paper_locomotion network and batch (ρ = 20, k = 4, h = 256; 128 × 100 samples, minibatches of 128, 10 passes:
1,000 minibatch steps) on the volume task, whose rollout needs no simulation. For each form of the trunk's two
convolutions (``agent.trunk``, ``FREEFORM_BENCH_UPDATE_VARIANTS``, default "conv gather fast": cuDNN, the gather
form of ``freeform.agents.networks.gather_trunk``, the sparse trunk's CSR products, what "auto" takes in a CUDA graph):

* agreement with ``conv`` on 128 design states (outputs and every parameter gradient, relative to their scale; on
  a GPU cuDNN's kernels compute in TF32) and whether two backward passes give the same bits;
* ms per minibatch, eager (2 passes) and as a CUDA graph (``agent.cuda_graph``, 10 passes), and the captured step's
  own GPU time (replays back to back, CUDA events): the rest is what the update spends outside the graph;
* the update's parts (flattening the rollout, the SGD passes, the statistics).

Then ``paper_locomotion`` epochs in the trainer with the trunks named in ``FREEFORM_BENCH_EPOCH_TRUNKS`` (default
"auto conv"). ``python -m benchmarks update`` on a CUDA machine (``scripts/gpu_check.sh ... update``); on the CPU
(``make bench``) the eager figures of the CPU's trunks at a small batch.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

from benchmarks.bench_gpu import line

NETWORK = ["experiment=paper_volume", "agent.hidden=256", "task.materials=4", "env.num_envs=128", "env.steps=100"]
SMALL = ["env.num_envs=16", "env.steps=20"]


def _build(variant: str, device: str, overrides: list[str]):
    from freeform.config import compose
    from freeform.run.build import build

    cfg = compose(*NETWORK, f"trainer.device={device}", f"agent.trunk={variant}", *overrides)
    _, ppo = build(cfg, torch.device(device))
    return cfg, ppo


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def agreement(variants: list[str], device: str, network: torch.nn.Module, grids: torch.Tensor) -> None:
    """Each variant of ``network`` (a ``VoxelActorCritic``) against its ``conv`` form on the same weights and
    ``grids``; whether two backward passes repeat their bits."""
    from freeform.agents.networks import VoxelActorCritic

    torch.manual_seed(0)
    reference = VoxelActorCritic(**{**network.init_kwargs, "trunk": "conv"}).to(device)
    with torch.no_grad():  # far from the init, so that every ReLU cuts somewhere
        for p in reference.parameters():
            p.copy_(torch.randn_like(p) * 0.3)

    def grads(net: torch.nn.Module) -> list[torch.Tensor]:
        net.zero_grad()
        mean, log_std, value = net(grids)
        (mean.square().sum() + log_std.sum() + (value - 1).square().sum()).backward()
        return [torch.cat([mean.flatten(), log_std.flatten(), value.flatten()]).detach()] + [
            p.grad.detach().clone() for p in net.parameters()]

    expected = grads(reference)
    for variant in variants:
        try:
            net = VoxelActorCritic(**{**network.init_kwargs, "trunk": variant}).to(device)
            net.load_state_dict(reference.state_dict())
            first, second = grads(net), grads(net)
        except Exception as e:
            line(f"{variant}: agreement", f"FAILED: {type(e).__name__}: {str(e)[:200]}")
            continue
        worst = max(float((a - b).abs().max() / b.abs().max().clamp_min(1.0)) for a, b in zip(first, expected, strict=True))
        same = all(torch.equal(a, b) for a, b in zip(first, second, strict=True))
        line(f"{variant} against conv: outputs and gradients (max rel.)", f"{worst:.1e}; twice the same bits: {same}")


def _timed(fn: Callable, times: dict[str, list[float]], name: str, device: str) -> Callable:
    def wrapper(*args, **kwargs):
        _sync(device)
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        _sync(device)
        times.setdefault(name, []).append(time.perf_counter() - t0)
        return out

    return wrapper


def update_figures(variant: str, device: str, rehearsal: bool) -> None:
    """Eager and CUDA-graph ms per minibatch of one variant, the captured step's GPU time, the update's parts."""
    size = SMALL if rehearsal else []
    modes = [("eager", ["agent.cuda_graph=false", f"agent.num_sgd_iter={1 if rehearsal else 2}"])]
    if device.startswith("cuda"):
        modes.append(("CUDA graph", ["agent.cuda_graph=true", "agent.num_sgd_iter=10"]))
    for mode, overrides in modes:
        try:
            cfg, ppo = _build(variant, device, size + overrides)
            times: dict[str, list[float]] = {}
            for part in ("_train_batch", "_sgd", "_update_stats"):
                setattr(ppo, part, _timed(getattr(ppo, part), times, part, device))
            ppo.collect()
            t0 = time.perf_counter()
            ppo.update()
            _sync(device)
            first = time.perf_counter() - t0
            times.clear()
            runs = []
            for _ in range(2):
                ppo.collect()
                _sync(device)
                t0 = time.perf_counter()
                ppo.update()
                _sync(device)
                runs.append(time.perf_counter() - t0)
            batch = cfg.env.num_envs * cfg.env.steps
            steps = cfg.agent.num_sgd_iter * (batch // min(cfg.agent.sgd_minibatch_size, batch))
            wall = statistics.median(runs)
            line(f"{variant}, {mode}: {steps} minibatches (first update {first:.1f} s)",
                 f"{wall / steps * 1e3:6.2f} ms a minibatch, {wall:.2f} s an update")
            parts = " | ".join(f"{k.strip('_')} {statistics.median(v) * 1e3:.0f}" for k, v in times.items())
            line("  parts, ms", parts)
            graphed = getattr(ppo, "_graphed", None)
            if graphed is not None and graphed._graphs:
                graph = next(iter(graphed._graphs.values()))
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                replays = 200
                start.record()
                for _ in range(replays):
                    graph.replay()
                end.record()
                torch.cuda.synchronize()
                gpu = start.elapsed_time(end) / replays
                line("  the captured step alone (GPU, replays back to back)",
                     f"{gpu:6.3f} ms; outside it {wall / steps * 1e3 - gpu:.3f} ms a minibatch")
        except Exception as e:  # one variant's failure is a figure too
            line(f"{variant}, {mode}", f"FAILED: {type(e).__name__}: {str(e)[:300]}")


def epochs(trunks: list[str], device: str) -> None:
    """``paper_locomotion`` in the trainer, 3 epochs a trunk (the first compiles): rollout and update seconds."""
    from freeform.config import compose
    from freeform.run.trainer import train

    for trunk in trunks:
        cfg = compose("experiment=paper_locomotion", f"trainer.device={device}", "trainer.epochs=3",
                      "trainer.progress=false", "trainer.checkpoint_every=0", f"agent.trunk={trunk}")
        try:
            with tempfile.TemporaryDirectory() as run:
                history = train(cfg, Path(run)).history
        except Exception as e:
            line(f"paper_locomotion, trunk={trunk}", f"FAILED: {type(e).__name__}: {str(e)[:300]}")
            continue
        for i, h in enumerate(history[1:], start=2):
            line(f"paper_locomotion epoch {i}, trunk={trunk}: rollout (simulation) | update",
                 f"{h['perf/time_rollout']:.2f} ({h.get('perf/sim_seconds', float('nan')):.2f}) | "
                 f"{h['perf/time_update']:.2f} s")


def main() -> None:
    arch = os.environ.get("FREEFORM_BENCH_ARCH", "cuda" if torch.cuda.is_available() else "cpu")
    device = "cuda" if arch == "cuda" else "cpu"
    rehearsal = device == "cpu"
    variants = os.environ.get("FREEFORM_BENCH_UPDATE_VARIANTS", "conv gather fast").split()
    _, ppo = _build("conv", device, SMALL + ["agent.cuda_graph=false"])
    net = ppo.policy
    print(f"  the paper_locomotion network (ρ = {net.resolution}, k = {net.materials}, h = {net.hidden}) on {device}"
          f"{f' ({torch.cuda.get_device_name()})' if device == 'cuda' else ''}", flush=True)
    ppo.collect()
    grids = ppo.rollout.obs.flatten(0, 1)[-128:].to(device)  # design states, late in their episodes
    agreement([v for v in variants if v != "conv"], device, net, grids)
    for variant in variants:
        update_figures(variant, device, rehearsal)
    if not rehearsal:
        epochs(os.environ.get("FREEFORM_BENCH_EPOCH_TRUNKS", "auto conv").split(), device)


if __name__ == "__main__":
    main()
