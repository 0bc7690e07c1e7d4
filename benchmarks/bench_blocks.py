"""The robots schedule as a thread block per robot against the flat schedule (issue 44; ``docs/physics.md``, "The
GPU"): µs a step at batch 1, 128 and 1,024 design bodies and a batch of 20³ cubes, B swept at batch 128, the epoch's
simulation, a control period (``Engine.control_step``) at N = 128 and 1,024 — each row flat and block side by side,
after a check that the block runs agree with flat and repeat bit for bit.

``python -m benchmarks blocks`` on a CUDA machine (B chosen per batch; under 3.5 minutes with a cold kernel cache).
``python -m benchmarks.bench_blocks --sweep`` (≈ 2 minutes): B from 64 to 512 at 128 and 1,024 bodies, flat against
block for 8³ and 12³ cubes (where ``auto`` changes schedule), and the trainer's paper epoch with ``auto`` kept flat
($FREEFORM_CUDA_ROBOTS=0) and as it picks. ``--rehearse`` (or ``FREEFORM_BENCH_ARCH=cpu``) runs either on the CPU at
tiny sizes, where "block" is the CPU's robots schedule (B = 1), the check's B = 32 runs the lanes in turn, and flat
launches from Python (no compute graph to build). Timings on a shared machine are indications: compare rows of one
run only.
"""

from __future__ import annotations

import math
import os
import sys
import time

import numpy as np
import torch

from benchmarks.bench_gpu import line
from freeform.sim import SimConfig, Simulator, runtime
from freeform.sim.engine import Engine
from freeform.sim.schedules import CUDA_ROBOTS_ENV

PAPER_SIM = dict(precision="f32", semantics="rl4design")  # the paper's simulation (bench_gpu.PAPER_SIM)
CONTROL_DT = 1e-4  # a control period of 100 steps at a fixed dt (bench_control)
EPOCH_BUDGET_S = 30.0  # the epoch's simulation on the block schedule is skipped when the batch-128 figure says longer


def design_bodies(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` bodies of an untrained design policy ``[n, ρ, ρ, ρ]`` (``bench_sim.random_design_bodies``)."""
    from benchmarks.bench_sim import random_design_bodies

    return random_design_bodies(n, seed=seed)


def engine_for(grids, cfg: SimConfig, arch: str, schedule: str, block_dim: int | None = None) -> Engine:
    """An ``Engine`` of ``grids`` on ``arch`` and ``schedule`` (``block_dim`` B for the block one)."""
    if arch == "cpu":  # (the rehearsal: a compute graph's build costs ~1 min per kernel variant on a busy 2-core CPU)
        cfg = SimConfig(**{**cfg.__dict__, "graph_launches": 0})
    sim = Simulator(cfg, arch=arch, schedule=schedule)
    return Engine(sim.layout(grids), cfg, arch=arch, schedule=schedule, arrays=sim.arrays, block_dim=block_dim)


def us_per_step(engine: Engine, steps: int, rounds: int = 3) -> float:
    """Best of ``rounds`` timed ``advance(steps)``, µs a step (after one untimed: compilation, the graph)."""
    engine.advance(steps)
    runtime.sync()
    best = math.inf
    for _ in range(rounds):
        t0 = time.perf_counter()
        engine.advance(steps)
        runtime.sync()
        best = min(best, (time.perf_counter() - t0) / steps * 1e6)
    return best


def check(arch: str, rehearsal: bool) -> None:
    """Block against flat on 6 design bodies and a 6³ cube (f32 rl4design, 300 steps): the largest difference of
    any voxel (voxel lengths: rounding, as between the CPU and CUDA); a second block run: the same bits."""
    grids = torch.zeros((7, 20, 20, 20), dtype=torch.uint8)
    grids[:6] = design_bodies(6, seed=5)
    grids[6, :6, :6, :6] = 2
    cfg = SimConfig(**PAPER_SIM, burn_in=100.0)
    runs = {}
    for name, schedule, block_dim in (("flat", "flat", None), ("block", "robots", None), ("block again", "robots", None),
                                      ("block B=32", "robots", 32)):
        t0 = time.perf_counter()
        engine = engine_for(grids, cfg, arch, schedule, block_dim)
        engine.advance(300)
        runs[name] = (engine.positions(), engine.robot_steps(), engine.block_dim)
        runtime.sync()
        what = f"{name} (B = {engine.block_dim})" if schedule == "robots" else name
        line(f"check: {what}, 300 steps, compilation included",
             f"{time.perf_counter() - t0:7.2f} s")
    flat = runs["flat"][0]
    for name in ("block", "block B=32"):
        d = np.abs(runs[name][0] - flat).max() / cfg.voxel_size
        same_steps = bool((runs[name][1] == runs["flat"][1]).all())
        line(f"check: {name} against flat, max |Δ position| (voxels); steps equal", f"{d:.2e}; {same_steps}")
    again = all(np.array_equal(a, b) for a, b in zip(runs["block"][:2], runs["block again"][:2], strict=True))
    line("check: block run twice, the same bits", str(again))


def step_rows(arch: str, rehearsal: bool) -> float:
    """µs a step, flat (compute graph) | block (B chosen per batch): design bodies and 20³ cubes; B swept at 128.
    Returns the block's µs a step at batch 128 (or the rehearsal's largest)."""
    cfg = SimConfig(**PAPER_SIM, burn_in=100.0)
    steps = 64 if rehearsal else 512
    block128 = math.nan
    for batch in ((1, 8) if rehearsal else (1, 128, 1024)):
        grids = design_bodies(batch)
        flat = us_per_step(engine_for(grids, cfg, arch, "flat"), steps)
        block_engine = engine_for(grids, cfg, arch, "robots")
        block = us_per_step(block_engine, steps)
        block128 = block if batch in (8, 128) else block128
        line(f"µs a step, {batch} design bodies: flat | block (B = {block_engine.block_dim})",
             f"{flat:8.1f} | {block:8.1f}")
    edge, n = (6, 2) if rehearsal else (20, 8)
    cubes = torch.full((n, edge, edge, edge), 2, dtype=torch.uint8)
    cube_cfg = SimConfig(precision="f32", burn_in=100.0)  # voxelyze, fixed dt: no serial ω² max on lane 0
    flat = us_per_step(engine_for(cubes, cube_cfg, arch, "flat"), steps // 4)
    block_engine = engine_for(cubes, cube_cfg, arch, "robots")
    block = us_per_step(block_engine, steps // 4)
    line(f"µs a step, {n} cubes of {edge}³ (voxelyze): flat | block (B = {block_engine.block_dim})",
         f"{flat:8.1f} | {block:8.1f}")
    if not rehearsal:
        grids = design_bodies(128)
        cells = [f"B={b}: {us_per_step(engine_for(grids, cfg, arch, 'robots', b), steps):.1f}" for b in (32, 64, 128)]
        line("µs a step, 128 design bodies, block by B", " | ".join(cells))
    return block128


def epoch_rows(arch: str, rehearsal: bool, block_us: float) -> None:
    """The epoch's simulation (``Simulator.simulate``: 128 bodies, 5 s + 5 s; the rehearsal 8, 0.05 s + 0.05 s)."""
    batch, protocol = (8, dict(burn_in=0.05, duration=0.05)) if rehearsal else (128, dict(burn_in=5.0, duration=5.0))
    cfg = SimConfig(**PAPER_SIM, **protocol)
    grids = design_bodies(batch)
    cells = []
    for schedule in ("flat", "robots"):
        if schedule == "robots" and not rehearsal and block_us * 92_418e-6 > EPOCH_BUDGET_S:
            cells.append(f"skipped (≈ {block_us * 92_418e-6:.0f} s at {block_us:.0f} µs a step)")
            continue
        t0 = time.perf_counter()
        run_cfg = SimConfig(**{**cfg.__dict__, "graph_launches": 0}) if rehearsal else cfg
        r = Simulator(run_cfg, arch=arch, schedule=schedule).simulate(grids)
        runtime.sync()
        cells.append(f"{time.perf_counter() - t0:6.2f} s ({int(r.steps.max())} steps)")
    line(f"the epoch's simulation, {batch} bodies, {cfg.burn_in:g} s + {cfg.duration:g} s: flat | block",
         " | ".join(cells))


def control_rows(arch: str, rehearsal: bool) -> None:
    """A control period of 100 steps in one call (``Engine.control_step``), ms: flat | block."""
    period = 100 * CONTROL_DT
    cfg = SimConfig(dt=CONTROL_DT, actuation="command", burn_in=0.0, duration=1000 * period)
    rounds = 3 if rehearsal else 10
    for n in ((8, 16) if rehearsal else (128, 1024)):
        grids = design_bodies(n)
        cells = []
        for schedule in ("flat", "robots"):
            engine = engine_for(grids, cfg, arch, schedule)
            zero = np.zeros(engine.layout.num_voxels)
            engine.control_step(zero, period)  # compile, build the graph
            t0 = time.perf_counter()
            for _ in range(rounds):
                engine.control_step(zero, period)
            cells.append(f"{(time.perf_counter() - t0) / rounds * 1e3:8.2f}")
        line(f"a control period of 100 steps, {n} bodies, ms: flat | block", " | ".join(cells))


def sweep_rows(arch: str, rehearsal: bool) -> None:
    """B swept at 128 and 1,024 design bodies; flat against block (B chosen) for cubes of 8³ and 12³ (where the
    largest robot's links say whether "auto" takes the block schedule: ``schedules.CUDA_AUTO_MAX_LINKS``)."""
    cfg = SimConfig(**PAPER_SIM, burn_in=100.0)
    steps = 64 if rehearsal else 512
    for batch in ((8,) if rehearsal else (128, 1024)):
        grids = design_bodies(batch)
        dims = (1, 2) if rehearsal else (64, 128, 256, 512)
        cells = [f"B={b}: {us_per_step(engine_for(grids, cfg, arch, 'robots', b), steps):.1f}" for b in dims]
        line(f"µs a step, {batch} design bodies, block by B", " | ".join(cells))
    cube_cfg = SimConfig(precision="f32", burn_in=100.0)
    for edge, n in (((4, 2),) if rehearsal else ((8, 16), (12, 16))):
        cubes = torch.full((n, edge, edge, edge), 2, dtype=torch.uint8)
        flat = us_per_step(engine_for(cubes, cube_cfg, arch, "flat"), steps // 4)
        block_engine = engine_for(cubes, cube_cfg, arch, "robots")
        block = us_per_step(block_engine, steps // 4)
        links = int(np.diff(block_engine.layout.link_start).max())
        line(f"µs a step, {n} cubes of {edge}³ ({links} links; voxelyze): flat | block (B = {block_engine.block_dim})",
             f"{flat:8.1f} | {block:8.1f}")


def app_epoch_rows(rehearsal: bool) -> None:
    """One paper_locomotion epoch as the trainer reports it (the second of two; CUDA-graph update), with the
    simulator's "auto" schedule kept flat ($FREEFORM_CUDA_ROBOTS=0) and as it now picks (the block schedule for
    the design env's bodies)."""
    import tempfile
    from pathlib import Path

    from freeform.config import compose
    from freeform.run.trainer import train

    preset = "experiment=locomotion_cpu" if rehearsal else "experiment=paper_locomotion"
    device = "cpu" if rehearsal else "cuda"
    extra = ("trainer.epochs=1",) if rehearsal else ("trainer.epochs=2", "agent.cuda_graph=true")
    for name, flag in (("flat", "0"), ("auto", "auto")):
        os.environ[CUDA_ROBOTS_ENV] = flag
        cfg = compose(preset, f"trainer.device={device}", "trainer.progress=false", "trainer.checkpoint_every=0", *extra)
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as run:
            last = train(cfg, Path(run)).history[-1]
        wall = time.perf_counter() - t0
        get = {k: last.get(k, math.nan) for k in ("perf/time_rollout", "perf/time_env", "perf/sim_seconds",
                                                   "perf/time_update")}
        line(f"{preset.split('=')[1]} epoch {cfg.trainer.epochs}, simulator {name}: "
             "rollout (env | simulation) | update",
             f"{get['perf/time_rollout']:6.2f} s ({get['perf/time_env']:.2f} | {get['perf/sim_seconds']:.2f}) | "
             f"{get['perf/time_update']:6.2f} s; {wall:.0f} s with compilation")
    os.environ[CUDA_ROBOTS_ENV] = "1"


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if "--rehearse" in argv:
        os.environ["FREEFORM_BENCH_ARCH"] = "cpu"
    os.environ.setdefault(CUDA_ROBOTS_ENV, "1")  # B chosen per batch (the rows name flat explicitly)
    arch = runtime.ensure(os.environ.get("FREEFORM_BENCH_ARCH", "auto"))
    rehearsal = arch == "cpu"
    print(f"{runtime.describe()} on {arch}, fast-math {'on' if runtime.fast_math() else 'off'}; "
          + (torch.cuda.get_device_name() if arch == "cuda" else f"CPU rehearsal, {runtime.num_threads()} threads: "
             "tiny sizes, block = the CPU's robots schedule") + f"; {CUDA_ROBOTS_ENV}={os.environ[CUDA_ROBOTS_ENV]}")
    t0 = time.perf_counter()
    if "--sweep" in argv:  # the second device call of issue 44: B, the auto threshold, the trainer's epoch
        sweep_rows(arch, rehearsal)
        app_epoch_rows(rehearsal)
        print(f"  (blocks --sweep: {time.perf_counter() - t0:.0f} s)")
        return
    check(arch, rehearsal)
    block_us = step_rows(arch, rehearsal)
    control_rows(arch, rehearsal)
    epoch_rows(arch, rehearsal, block_us)
    print(f"  (blocks: {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
