"""The native schedule (``freeform/sim/native.py``): the CPU's step compiled by the host's C++ compiler, checked
against the robots schedule — Taichi's kernels, which the reference tests hold to Voxelyze's values.

The native step is the fast-math f32 path's, so its agreement tests run in ``make test``'s fast-math stage (this
file is in its list) and skip on the strict path, where the refusal is what is tested. Both run Voxelyze's
arithmetic, contracted differently, so they agree as two fast-math compilers do (``tests/test_backends.py``'s
tolerances for Taichi against quadrants): measured here 1.4e-4 voxel lengths and 1.0e-6 m over 0.5 s of six design
bodies, ~10x inside them.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from freeform.sim import SimConfig, Simulator, native, runtime
from freeform.sim.schedules import resolve_schedule
from freeform.sim.state import BUFFERS, HDR, LR, VR
from freeform.sim.terrain import Terrain

ROOT = Path(__file__).resolve().parents[1]
ATOL_DISPLACEMENT = 1e-3  # voxel lengths (tests/test_backends.py: two fast-math compilers)
ATOL_COM_M = 1e-5
fast_math_only = pytest.mark.skipif(not runtime.fast_math(), reason="the native step is the fast-math path's: it runs "
                                    "in make test's fast-math stage (FREEFORM_FAST_MATH=1)")
needs_compiler = pytest.mark.skipif(native.compiler() is None, reason="no C++ compiler (g++ or $CXX)")


def design_bodies(n: int = 6, seed: int = 3) -> np.ndarray:
    """Bodies of an untrained design policy (the benchmark's, ``DesignEnv`` at ρ = 20)."""
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies

    return random_design_bodies(n, seed=seed).numpy()


def test_what_the_native_step_does_not_run_is_refused_naming_it():
    with pytest.raises(ValueError, match="schedule='native' is the CPU's"):
        resolve_schedule("native", "cuda")
    with pytest.raises(ValueError, match=r"SimConfig.schedule must be one of \('auto', 'robots', 'flat', 'native'\)"):
        SimConfig(schedule="fastest").validate()
    grids = design_bodies(1)
    refused = {"precision='f64'": SimConfig(precision="f64", schedule="native")}
    if runtime.fast_math():
        refused.update({"semantics='rl4design'": SimConfig(semantics="rl4design", schedule="native"),
                        "a terrain": SimConfig(terrain=Terrain(kind="slope", degrees=5.0), schedule="native")})
    else:
        refused["FREEFORM_FAST_MATH=0"] = SimConfig(schedule="native")
    for why, cfg in refused.items():
        sim = Simulator(cfg, arch="cpu")
        with pytest.raises(ValueError, match=rf"schedule='native' does not run {why}.*use schedule='robots'"):
            sim.engine(sim.layout(grids))


@fast_math_only
@needs_compiler
def test_the_native_step_agrees_with_the_robots_schedule():
    """0.5 s of six design bodies, the sine's gait, by ``Simulator.simulate`` (``sim.schedule``) with a trace: the
    same steps and statuses, displacements and centres of mass within two fast-math compilers' tolerance, the
    trace's every sample too."""
    cfg = SimConfig(burn_in=0.1, duration=0.4)
    got = {s: Simulator(replace(cfg, schedule=s), arch="cpu").simulate(design_bodies(), trace_every=0.05)
           for s in ("robots", "native")}
    robots, ours = got["robots"], got["native"]
    np.testing.assert_array_equal(ours.steps.numpy(), robots.steps.numpy())
    np.testing.assert_array_equal(ours.diverged.numpy(), robots.diverged.numpy())
    assert not robots.diverged.any() and (robots.displacement > 0.3).all()  # (they walk: a test that can fail)
    np.testing.assert_allclose(ours.displacement.numpy(), robots.displacement.numpy(), atol=ATOL_DISPLACEMENT)
    np.testing.assert_allclose(ours.com_end.numpy(), robots.com_end.numpy(), atol=ATOL_COM_M)
    np.testing.assert_array_equal(ours.trace.time, robots.trace.time)
    np.testing.assert_array_equal(ours.trace.valid, robots.trace.valid)
    assert robots.trace.com.shape[1] >= 10
    np.testing.assert_allclose(ours.trace.com, robots.trace.com, atol=ATOL_COM_M)
    np.testing.assert_allclose(ours.trace.orientation, robots.trace.orientation, atol=1e-4)


@fast_math_only
@needs_compiler
@pytest.mark.parametrize("actuation", ["command", "residual"])
def test_native_control_steps_agree_with_the_robots_schedule(actuation):
    """Closed-loop control's path: ``Engine.control_step`` (commands, a ramp over the period, the senses read back)
    for 12 periods of random commands, on both schedules from the same bodies: the same clocks, senses within
    tolerance."""
    cfg = SimConfig(actuation=actuation, burn_in=0.0, duration=10.0)
    engines = {}
    for s in ("robots", "native"):
        sim = Simulator(replace(cfg, schedule=s), arch="cpu")
        engines[s] = sim.engine(sim.layout(design_bodies(4, seed=1)))
    rng = np.random.default_rng(0)
    for _ in range(12):
        commands = rng.uniform(-1.0, 1.0, engines["robots"].layout.num_voxels)
        readouts = {s: e.control_step(commands, 0.025, ramp=0.025) for s, e in engines.items()}
    np.testing.assert_array_equal(engines["native"].robot_time(), engines["robots"].robot_time())
    np.testing.assert_array_equal(engines["native"].robot_status(), engines["robots"].robot_status())
    moved = np.abs(engines["robots"].positions() - engines["robots"].layout.lattice * cfg.voxel_size).max()
    assert moved > 1e-3  # (0.3 s of random commands moves them: a test that can fail)
    np.testing.assert_allclose(engines["native"].positions(), engines["robots"].positions(), atol=ATOL_COM_M)
    np.testing.assert_array_equal(readouts["native"].time, readouts["robots"].time)
    np.testing.assert_allclose(readouts["native"].com, readouts["robots"].com, atol=ATOL_COM_M)
    # positions relative to the centre of mass (m) and the contacts as the COM; velocities (m/s) and strains looser
    np.testing.assert_allclose(readouts["native"].voxels, readouts["robots"].voxels, atol=1e-3)


def lanes_against_scalar() -> dict:
    """One step of every link and voxel of a walking batch (24 design bodies after 300 steps) from one state by the
    vector path (``link_group``, ``voxel_group``: a group of lanes per instruction) and by the branching updates that
    mirror Taichi's (``link_update``, ``voxel_update``): {"slow": item-steps off the vector path, "items",
    "worst": {column: max |vector − scalar| / max |scalar|}, "changed": whether the step changed the state}."""
    sim = Simulator(SimConfig(dt=1.1785e-4, burn_in=0.0, duration=10.0, schedule="native"), arch="cpu")
    engine = sim.engine(sim.layout(design_bodies(24, seed=0)))
    engine.advance(300)
    start = engine.snapshot()["buffers"]
    lib = native.library()
    out = {}
    for how in ("links_voxels_scalar", "links_voxels_vector"):
        state = {k: v.copy() for k, v in start.items()}
        slow = getattr(lib, how)(*(state[k].ctypes.data for k in BUFFERS), 1, 1)
        out[how] = state, slow
    (one, _), (lanes, slow) = out["links_voxels_scalar"], out["links_voxels_vector"]
    h = start["ints"]
    worst, changed = {}, True
    for region, table, n, columns in (("lr", LR, h[HDR.N_LINKS], ("FN", "FP", "MN", "MP", "P2", "A1", "A2", "STRAIN")),
                                      ("vr", VR, h[HDR.N_VOXELS], ("POS", "MOM", "ORI", "AMOM", "TAREA", "TSUM",
                                                                   "SIZE"))):
        at = h[getattr(HDR, f"{region.upper()}_AT")]
        a, b, before = (s["reals"][at: at + n * table.width].reshape(n, table.width) for s in (lanes, one, start))
        for col in columns:
            x, y = (m[:, table.span(col)].astype(np.float64) for m in (a, b))
            worst[f"{region}.{col}"] = float(np.abs(x - y).max() / max(np.abs(y).max(), 1e-30))
        changed &= not np.array_equal(a, before)
    return {"slow": int(slow), "items": int(h[HDR.N_LINKS] + h[HDR.N_VOXELS]), "worst": worst, "changed": changed}


def check_lanes_against_scalar(got: dict) -> None:
    """The vector path agrees with the scalar one to rounding (measured: the end loads within 1.2e-5 of their
    largest, the damping scaling a difference of successive poses; positions 3e-8) and takes most item-steps (it is
    what makes the schedule fast; a path that silently fell back would pass every other test)."""
    assert got["slow"] < 0.4 * got["items"], f"{got['slow']} of {got['items']} item-steps left the vector path"
    for col, worst in got["worst"].items():
        assert worst <= 1e-4, f"{col}: {worst:.1e}"
    assert got["changed"]


@fast_math_only
@needs_compiler
def test_a_group_of_lanes_equals_one_at_a_time_and_takes_most_items():
    """This host's build (``native.built_for``): the vector path against the scalar one (``lanes_against_scalar``)."""
    check_lanes_against_scalar(lanes_against_scalar())


def test_auto_takes_the_native_step_on_the_cpu_where_it_runs():
    """``schedule="auto"`` on the CPU (``resolve_schedule``, the one place that decides): the native step for what
    it runs (the fast-math f32 path, with a compiler) where its build is measured the faster (an AVX2 or AVX-512
    host), the robots schedule for the rest (f64 here; the strict path in make test's first stage)."""
    grids = design_bodies(1)
    runs = runtime.fast_math() and native.compiler() is not None and "AVX2" in runtime.cpu_features()
    for cfg, expected in ((SimConfig(), "native" if runs else "robots"), (SimConfig(precision="f64"), "robots")):
        sim = Simulator(cfg, arch="cpu")
        assert sim.engine(sim.layout(grids)).schedule == expected, cfg.precision
    assert resolve_schedule("auto", "cpu") == "robots"  # (no batch known yet: nothing chosen)


def other_builds() -> list[str]:
    """The instruction sets this host runs besides its own build's: AVX2 (x86-64-v3, 8 lanes) on an AVX-512 host,
    and everywhere x86-64-v2 (SSE4.2: 4 lanes of GCC's generic vectors, what a NEON build compiles to)."""
    features = runtime.cpu_features()
    return (["x86-64-v3"] if "AVX512F" in features else []) + (["x86-64-v2"] if "SSE42" in features else [])


CHILD = """import json, sys; sys.path.insert(0, sys.argv[1])
from freeform.sim import SimConfig, Simulator, native
from tests.test_native import design_bodies, lanes_against_scalar
r = Simulator(SimConfig(burn_in=0.1, duration=0.4, schedule='native'), arch='cpu').simulate(design_bodies())
print(json.dumps({'built_for': native.built_for(), 'auto_native': native.faster_here(), 'steps': r.steps.tolist(),
                  'displacement': r.displacement.tolist(), 'com': r.com_end.tolist(), 'lanes': lanes_against_scalar()}))
"""


@fast_math_only
@needs_compiler
def test_builds_for_other_instruction_sets_agree():
    """Every build this host runs besides its own (``other_builds``; $FREEFORM_NATIVE_ARCH), each in a process of
    its own (the library is built once per process; cached as any build is, so a later run loads it), the processes
    at once: 0.5 s of six design bodies against the robots schedule here, to the agreement test's tolerances, and
    its vector path against its scalar one."""
    import json
    import os
    import subprocess

    children = {}
    for arch in other_builds():
        env = {**os.environ, "FREEFORM_NATIVE_ARCH": arch}
        children[arch] = subprocess.Popen([sys.executable, "-c", CHILD, str(ROOT)], stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, text=True, env=env)
    robots = Simulator(SimConfig(burn_in=0.1, duration=0.4, schedule="robots"), arch="cpu").simulate(design_bodies())
    for arch, child in children.items():
        out, err = child.communicate(timeout=300)
        assert child.returncode == 0, err[-3000:]
        theirs = json.loads(out.strip().splitlines()[-1])
        lanes = {"x86-64-v3": 8, "x86-64-v2": 4}[arch]
        assert f"-march={arch}" in theirs["built_for"], theirs["built_for"]
        assert f"{lanes} lanes" in theirs["built_for"] and theirs["auto_native"] == (lanes == 8), theirs["built_for"]
        np.testing.assert_array_equal(theirs["steps"], robots.steps.numpy())
        np.testing.assert_allclose(theirs["displacement"], robots.displacement.numpy(), atol=ATOL_DISPLACEMENT)
        np.testing.assert_allclose(theirs["com"], robots.com_end.numpy(), atol=ATOL_COM_M)
        check_lanes_against_scalar(theirs["lanes"])
