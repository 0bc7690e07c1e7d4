"""Simulator throughput in voxel-steps per second (voxels × steps / time; kernels compiled beforehand).

Figures: a batch of 128 bodies designed by N(0, I) actions through the real ``DesignEnv`` (k = 4 materials,
ρ = 20, T = 100 actions, b = 2; the body is the largest component, ``info["bodies"]`` at the last step); a batch of
muscle cubes of 10³; throughput against batch size (1 … 512 design bodies) and against body size (5³, 10³, 20³);
the 128 design bodies on rough ground, stairs and a slope against flat ground (kernels only, alternated).
Voxelyze does 2.2-3.0 M voxel-steps/s on one core of the reference machine (spec section 15).

Every figure is given twice: per wall-clock second (what a user waits) and per CPU second of this process
(``time.process_time``, all threads) — on a shared machine the wall figure mostly measures the other tenants,
while the CPU-second figure is what the engine does with the core time it actually receives.

Every row runs on each simulator backend (Taichi 1.7.4 and, where installed, quadrants; ``freeform.sim.runtime``)
side by side. The two cannot share a process, so each backend is a worker subprocess kept for the whole run (its
kernels compiled once, before any timing), and every row is measured on one backend and then at once on the other,
so that both see the same machine load; the load average is printed with each row.

``python -m benchmarks sim``; environment: ``FREEFORM_BENCH_PRECISION=f64`` measures double precision
(``f32,f64`` both, in one run), ``FREEFORM_BENCH_BACKENDS=taichi`` one backend only (default: both where quadrants
is installed), ``FREEFORM_BENCH_SCALE=0.2`` shortens every run (a quick look; launch overheads then weigh more),
``FREEFORM_BENCH_TREES=before=/tmp/ff-before,after=.`` runs every row on each named checkout of freeform too (a
worker per checkout and backend, alternated like the backends: a before/after comparison in one run; make the
"before" checkout with ``git archive REF | tar -x -C DIR``). The native schedule (``sim.schedule=native``: the
step compiled by the host's C++ compiler, ``freeform/sim/native.py``) gets a column beside the robots schedule where
a compiler is found (on the first backend); ``FREEFORM_BENCH_SCHEDULES=robots,native`` runs every backend on each
(rows it does not run, f64 and terrains, print nan); the first line names the instruction set and lanes the native
step was built for (``FREEFORM_NATIVE_ARCH=x86-64-v3``: the AVX2 build, whatever the host).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from freeform.evolve import untrained_design_bodies
from freeform.sim import SimConfig, Simulator, Terrain, native

RHO, K, T_ACTIONS, BUNDLE = 20, 4, 100, 2  # the paper's locomotion design setting (design.md)
DT = 1.1785e-4  # the recommended step of the paper's materials × 0.95 (every robot with links gets this)
# voxel-steps per measurement: long enough to dwarf launch and layout overheads, short enough for ~2 min in all
TARGET_VOXEL_STEPS = 3.5e7 * float(os.environ.get("FREEFORM_BENCH_SCALE", "1"))


def random_design_bodies(n: int, seed: int = 0) -> torch.Tensor:
    """Bodies of an untrained policy in the paper's design setting (``untrained_design_bodies``; no fallback: if the
    environment breaks, this does)."""
    return untrained_design_bodies(n, RHO, K, T_ACTIONS, BUNDLE, seed)


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


TERRAINS = {"flat": Terrain.flat(), "rough (3 mm, 4 cm)": Terrain.rough(0.003, 0.04),
            "stairs (3 mm, 2 cm)": Terrain.steps(0.003, 0.02), "slope 5 deg": Terrain.slope(5)}
TERRAIN_ROUNDS = 3  # best of this many alternated runs per terrain


def rows(precisions: list[str]) -> list[tuple[str, str, dict]]:
    """Every measurement, in the order printed: (section, label, what the worker runs)."""
    out = []
    for p in precisions:
        sec = f"{p}: 128 design bodies, cubes"
        out += [(sec, "128 N(0,I) design bodies", {"p": p, "kind": "simulate", "bodies": 128}),
                (sec, "  the same, kernels only", {"p": p, "kind": "kernels", "bodies": 128}),
                (sec, "32 muscle cubes 10^3", {"p": p, "kind": "simulate", "cubes": [32, 10, 2]})]
        sec = f"{p}: terrain (128 design bodies, kernels only, best of {TERRAIN_ROUNDS} alternated runs)"
        for i in range(TERRAIN_ROUNDS):
            out += [(sec, name, {"p": p, "kind": "kernels", "bodies": 128, "terrain": name, "round": i,
                                 "rounds": TERRAIN_ROUNDS}) for name in TERRAINS]
        sec = f"{p}: batch size (N(0,I) design bodies, whole simulate)"
        out += [(sec, f"B={b}", {"p": p, "kind": "simulate", "bodies": b}) for b in (1, 8, 32, 128, 512)]
        sec = f"{p}: body size (passive cubes)"
        out += [(sec, f"{b} cubes {n}^3", {"p": p, "kind": "simulate", "cubes": [b, n, 1]})
                for n, b in ((5, 64), (10, 16), (20, 4))]
    return out


def built_for(schedule: str) -> str:
    """What the native step is built for (instruction set, lanes, -march) where a worker on ``schedule`` may run it
    ("auto", "native"; $FREEFORM_NATIVE_ARCH chooses another build), as its column's header says; else ""."""
    if schedule not in ("auto", "native") or not native.available():
        return ""
    taken = schedule == "native" or native.faster_here()
    return f"; native step {'' if taken else 'not taken, '}built for {native.built_for()}"


def worker() -> None:
    """A backend's worker (``FREEFORM_BACKEND`` set by ``main``): one JSON request per line on stdin, one JSON
    answer per line on stdout: (wall, cpu) M voxel-steps/s, voxels, steps."""
    from freeform.sim import runtime

    bodies = random_design_bodies(512, seed=0)
    schedule = os.environ.get("FREEFORM_BENCH_SCHEDULE", "auto")
    sims: dict[tuple[str, str], Simulator] = {}
    real_stdout = sys.stdout
    sys.stdout = sys.stderr  # the backends' banners and anything else printed stay off the answer channel
    for line in sys.stdin:
        req = json.loads(line)
        if req.get("kind") == "info":
            runtime.ensure("auto")
            ans = {"backend": runtime.describe(), "arch": runtime.ensure("auto"), "threads": runtime.num_threads(),
                   "native": built_for(schedule)}
            print(json.dumps(ans), file=real_stdout, flush=True)
            continue
        key = (req["p"], req.get("terrain", "flat"))
        if key not in sims:
            sims[key] = Simulator(SimConfig(precision=req["p"], terrain=TERRAINS[key[1]], schedule=schedule),
                                  arch="auto")
            try:
                throughput(sims[key], bodies[:2])  # compile (or load from the offline cache) outside the timings
                engine_throughput(sims[key], bodies[:2], 20)
            except ValueError:  # (what this schedule does not run: native's f64 and terrains)
                sims[key] = None
        sim = sims[key]
        if sim is None:
            print(json.dumps({"wall": float("nan"), "cpu": float("nan"), "voxels": 0, "steps": 0}), file=real_stdout,
                  flush=True)
            continue
        grids = bodies[:req["bodies"]] if "bodies" in req else cubes(*req["cubes"])
        if req["kind"] == "simulate":
            rate, crate, nv, st = throughput(sim, grids)
        else:
            nv = int((grids > 0).sum())
            st = max(200, int(TARGET_VOXEL_STEPS / nv / req.get("rounds", 1)))
            rate, crate = engine_throughput(sim, grids, st)
        print(json.dumps({"wall": rate / 1e6, "cpu": crate / 1e6, "voxels": nv, "steps": st}), file=real_stdout,
              flush=True)


def cell(wall: float, cpu: float) -> str:
    """A row's figures for one column, or that the column's schedule does not run the row (NaN from the worker:
    native's f64 and terrains), never a number that was not measured."""
    return f"  {'not run':>15s}" if math.isnan(wall) else f"  {wall:6.2f} | {cpu:6.2f}"


def best_of(old: tuple[float, float] | None, wall: float, cpu: float) -> tuple[float, float]:
    """The best of alternated rounds so far (a row its column does not run stays NaN)."""
    return (wall, cpu) if old is None or math.isnan(old[0]) else (max(old[0], wall), max(old[1], cpu))


class Worker:
    """A worker subprocess on one backend and schedule, running the freeform of checkout ``tree`` (default: this
    one)."""

    def __init__(self, backend: str, tree: str | None = None, schedule: str = "auto"):
        root = Path(tree).resolve() if tree else Path(__file__).resolve().parents[1]
        path = os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p)
        env = {**os.environ, "FREEFORM_BACKEND": backend, "PYTHONPATH": path, "FREEFORM_BENCH_SCHEDULE": schedule}
        self.proc = subprocess.Popen([sys.executable, "-m", "benchmarks.bench_sim", "--worker"], env=env, text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                     cwd=root)

    def ask(self, req: dict) -> dict:
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"benchmark worker died on {req} (run it alone: FREEFORM_BACKEND=... python -m "
                               f"benchmarks.bench_sim --worker)")
        return json.loads(line)

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def main() -> None:
    precisions = os.environ.get("FREEFORM_BENCH_PRECISION", "f32").split(",")
    default = "taichi,quadrants" if importlib.util.find_spec("quadrants") is not None else "taichi"
    names = os.environ.get("FREEFORM_BENCH_BACKENDS", default).split(",")
    trees = [t.split("=", 1) for t in os.environ.get("FREEFORM_BENCH_TREES", "").split(",") if t]
    # a column per backend, or per (checkout, backend) with FREEFORM_BENCH_TREES; and per schedule
    columns = {f"{b}@{label}": (b, tree, "auto") for label, tree in trees for b in names} if trees else \
        {b: (b, None, "auto") for b in names}
    if "FREEFORM_BENCH_SCHEDULES" in os.environ:
        columns = {f"{c}/{s}": (b, tree, s) for c, (b, tree, _) in columns.items()
                   for s in os.environ["FREEFORM_BENCH_SCHEDULES"].split(",")}
    elif native.compiler() is not None and not trees:
        columns[f"{names[0]}/native"] = (names[0], None, "native")
    backends = list(columns)
    workers = {c: Worker(*columns[c]) for c in backends}
    try:
        infos = {b: w.ask({"kind": "info"}) for b, w in workers.items()}
        for b in backends:  # warm every simulator before any timing (compile or load the kernel cache)
            for p in precisions:
                for terrain in TERRAINS:
                    workers[b].ask({"p": p, "kind": "kernels", "bodies": 2, "terrain": terrain})
        print(", ".join(f"{b}: {i['backend']} ({i['arch']}, {i['threads']} threads{i.get('native', '')})"
                        for b, i in infos.items())
              + f" on {os.cpu_count()} CPU cores; load average {os.getloadavg()[0]:.1f} at the start")
        print("M voxel-steps/s per wall second | per CPU second (wall is pessimistic on a shared machine); each row "
              "runs on every backend in turn (who goes first alternates); the last column is the load average")
        head = "".join(f"{b:>17s}" for b in backends)
        best: dict[tuple[str, str, str], tuple[float, float]] = {}
        section = None
        for i, (sec, label, req) in enumerate(rows(precisions)):
            if sec != section:
                print(f"{sec}:\n  {'':34s} {'':23s}{head}", flush=True)
                section = sec
            order = backends if i % 2 == 0 else backends[::-1]  # who goes first alternates from row to row
            got = {b: workers[b].ask(req) for b in order}
            got = {b: got[b] for b in backends}
            if "terrain" in req:
                for b, g in got.items():
                    best[(sec, label, b)] = best_of(best.get((sec, label, b)), g["wall"], g["cpu"])
                if label != list(TERRAINS)[-1] or req["round"] != TERRAIN_ROUNDS - 1:
                    continue
                for name in TERRAINS:
                    cells = "".join(cell(*best[(sec, name, b)]) for b in backends)
                    flat = best[(sec, "flat", backends[0])][1]
                    cost = 100 * (flat / best[(sec, name, backends[0])][1] - 1)
                    print(f"  {name:<34s} {f'({cost:+5.1f} % time vs flat)':>23s}{cells}"
                          f"  (load {os.getloadavg()[0]:.1f})", flush=True)
                continue
            g0 = got[backends[0]]
            cells = "".join(cell(g["wall"], g["cpu"]) for g in got.values())
            print(f"  {label:<34s} voxels={g0['voxels']:6d} steps={g0['steps']:5d}{cells}"
                  f"  (load {os.getloadavg()[0]:.1f})", flush=True)
        print(f"load average {os.getloadavg()[0]:.1f} at the end")
    finally:
        for w in workers.values():
            w.close()


if __name__ == "__main__":
    if sys.argv[1:] == ["--worker"]:
        worker()
    else:
        main()
