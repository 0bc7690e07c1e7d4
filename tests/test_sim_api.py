"""Simulator API: layout, validation, batching, robustness, recording format."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freeform.sim import Material, SimConfig, Simulator, build_layout, recommended_dt
from freeform.sim.engine import Engine
from freeform.sim.schedules import CUDA_ROBOTS_ENV, block_dim_for, resolve_schedule
from freeform.sim.state import BUFFERS, DIVERGED, LT, RUNNING, VR


def short(**kw) -> SimConfig:
    kw.setdefault("burn_in", 0.05)
    kw.setdefault("duration", 0.1)
    return SimConfig(**kw)


# ---------------------------------------------------------------- initial state (pure numpy)
def test_initial_state_is_numpy_alone_with_hand_worked_values():
    """A muscle pair along x, at t = 0: positions on the lattice, rest sizes, the static-friction start of VX (not of
    rl4design), the link's material pair, the clock, and step 0's events — built without importing any backend."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from freeform.sim import SimConfig, build_layout\n"
            "from freeform.sim.initial import initial_state\n"
            "g = np.zeros((1, 2, 1, 1), np.uint8); g[0, 0, 0, 0], g[0, 1, 0, 0] = 2, 3\n"
            "s = initial_state(build_layout(g, 4), SimConfig(dt=1e-4, burn_in=0.0, temp_amplitude=0.0))\n"
            "assert not {'taichi', 'quadrants'} & set(sys.modules), sorted(m for m in sys.modules if 'taichi' in m)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]

    from freeform.sim.initial import initial_state
    from freeform.sim.state import EV_SAMPLE, EV_START, LI, RI, RT, STATIC, VI

    g = np.zeros((1, 2, 1, 1), np.uint8)
    g[0, 0, 0, 0], g[0, 1, 0, 0] = 2, 3
    cfg = SimConfig(dt=1e-4, burn_in=0.0, temp_amplitude=0.0, precision="f64")
    s = initial_state(build_layout(g, 4), cfg)
    vr, vi, li, rt, ri = (s.tables[k] for k in ("vr", "vi", "li", "rt", "ri"))
    np.testing.assert_array_equal(vr[VR.span("POS")].T, [[0, 0, 0], [cfg.voxel_size, 0, 0]])
    np.testing.assert_array_equal(vr[VR.SIZE], [cfg.voxel_size] * 2)  # T = 0: the rest size is L
    assert (vi[VI.FLAGS] & STATIC).all() and list(vi[VI.MAT]) == [2, 3]
    assert li[LI.LMAT, 0] == 2 * 4 + 3  # (negative end, positive end) of 4 materials
    assert rt[RT.DT, 0] == 1e-4 and ri[RI.VSTART, 0] == 0 and ri[RI.VEND, 0] == 2
    assert ri[RI.EVENTS, 0] & EV_START  # burn-in 0: the window opens with step 0
    assert ri[RI.PERIOD, 0] == int(cfg.temp_period / 1e-4) and not ri[RI.EVENTS, 0] & EV_SAMPLE
    rl = initial_state(build_layout(g, 4), SimConfig(dt=1e-4, semantics="rl4design"))
    assert not (rl.tables["vi"][VI.FLAGS] & STATIC).any() and rl.switches.rl4design == 1
    assert rl.switches.dynamic_dt == 0  # dt fixed


# ---------------------------------------------------------------- layout
def test_layout_crops_places_on_floor_and_links_faces():
    g = np.zeros((3, 5, 5, 5), dtype=np.uint8)
    g[0, 2:4, 1, 3] = 1  # two voxels along x, floating at z = 3
    g[0, 3, 1, 4] = 2  # one above the second
    g[2, 4, 4, 4] = 3  # a single voxel in the corner
    lay = build_layout(g, 3)
    assert lay.num_robots == 2 and lay.num_bodies == 3
    np.testing.assert_array_equal(lay.robot_of_body, [0, -1, 1])
    np.testing.assert_array_equal(lay.lattice, [[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 0]])
    np.testing.assert_array_equal(lay.material, [1, 1, 2, 3])
    # links: x between voxels 0-1, z between 1-2; none for the single voxel
    np.testing.assert_array_equal(lay.link_neg, [0, 1])
    np.testing.assert_array_equal(lay.link_pos, [1, 2])
    np.testing.assert_array_equal(lay.link_axis, [0, 2])
    np.testing.assert_array_equal(lay.slots[1], [-1, 0, -1, -1, 1, -1])  # X_NEG = link 0, Z_POS = link 1
    np.testing.assert_array_equal(lay.voxel_start, [0, 3, 4])
    np.testing.assert_array_equal(lay.link_start, [0, 2, 2])


def test_layout_link_count_of_a_cube():
    lay = build_layout(np.ones((2, 3, 3, 3), dtype=np.uint8), 1)
    assert lay.num_links == 2 * 3 * (2 * 3 * 3)  # per cube: 3 axes × 2 × 3 × 3
    assert (lay.slots >= 0).sum() == 2 * lay.num_links


def test_recommended_dt_matches_spec():
    cfg = SimConfig()
    lay = build_layout(np.stack([np.ones((2, 2, 2)), np.pad(np.ones((1, 1, 1)), ((0, 1), (0, 1), (0, 1)))])
                       .astype(np.uint8), 3)
    np.testing.assert_allclose(recommended_dt(lay, cfg), [1.240490e-4, 1.949242e-4], rtol=1e-6)
    cfg0 = SimConfig(materials=[Material(poisson=0.0)])
    np.testing.assert_allclose(recommended_dt(build_layout(np.ones((1, 2, 1, 1), np.uint8), 1), cfg0),
                               [1.949242e-4], rtol=1e-6)


# ---------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "grids, match",
    [
        (np.ones((1, 2, 2, 2), dtype=np.int64), "uint8"),
        (np.ones((2, 2, 2), dtype=np.uint8), "rank 4"),
        (np.full((1, 2, 2, 2), 4, dtype=np.uint8), "material index 4"),
        ([[1]], "torch.Tensor or np.ndarray"),
    ],
)
def test_invalid_grids_raise_value_error(grids, match):
    with pytest.raises(ValueError, match=match):
        Simulator(short(), arch="cpu").simulate(grids)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"reward": "speed"}, "reward"),
        ({"semantics": "vx3"}, "semantics"),
        ({"precision": "f16"}, "precision"),
        ({"dt": -1.0}, "dt"),
        ({"materials": []}, "materials"),
        ({"materials": [Material(poisson=0.5)]}, "poisson"),
        ({"step_cap": 1.0}, "step_cap"),
    ],
)
def test_invalid_config_raises_value_error(kw, match):
    with pytest.raises(ValueError, match=match):
        Simulator(SimConfig(**kw))


def test_invalid_arch_and_schedule():
    with pytest.raises(ValueError, match="arch"):
        Simulator(short(), arch="tpu").simulate(np.ones((1, 1, 1, 1), np.uint8))
    with pytest.raises(ValueError, match="schedule"):
        Simulator(short(), arch="cpu", schedule="fast").simulate(np.ones((1, 1, 1, 1), np.uint8))
    with pytest.raises(ValueError, match="record_every"):
        Simulator(short(), arch="cpu").simulate(np.ones((1, 1, 1, 1), np.uint8), record_every=0)


def test_auto_picks_the_block_schedule_on_cuda_for_small_robots(monkeypatch):
    """On CUDA "auto" takes the thread block per robot where it was measured faster than flat (robots of at most
    CUDA_AUTO_MAX_LINKS links: the design env's bodies, cubes up to 8³) and flat beyond or where
    FREEFORM_CUDA_ROBOTS=0 says so (checked without a GPU by passing the arch). B: each lane a couple of links of the
    largest robot, fewer lanes in a big batch (H100: 256 best at 128 design bodies, 128 at 1,024), or the one named."""
    monkeypatch.delenv(CUDA_ROBOTS_ENV, raising=False)
    assert resolve_schedule("auto", "cuda", 388) == "robots" and resolve_schedule("auto", "cuda", 1344) == "flat"
    assert resolve_schedule("auto", "cuda") == "flat"  # a Simulator before its first batch: nothing chosen yet
    assert resolve_schedule("robots", "cuda") == "robots" and resolve_schedule("flat", "cuda", 10) == "flat"
    assert resolve_schedule("auto", "cpu") == "robots" and resolve_schedule("flat", "cpu") == "flat"
    assert Simulator(short(), arch="cuda", schedule="robots").schedule == "robots"  # refused nothing, started nothing
    assert [block_dim_for(m) for m in (0, 50, 64, 65, 388, 530, 1344, 22800)] == [32, 32, 32, 64, 256, 512, 512, 512]
    assert [block_dim_for(530, n) for n in (1, 128, 256, 1024, 4096, 10**6)] == [512, 512, 512, 128, 32, 32]
    monkeypatch.setenv(CUDA_ROBOTS_ENV, "0")
    assert resolve_schedule("auto", "cuda", 388) == "flat" and resolve_schedule("robots", "cuda") == "robots"
    monkeypatch.setenv(CUDA_ROBOTS_ENV, "64")
    assert block_dim_for(22800) == 64 and resolve_schedule("auto", "cuda", 388) == "robots"
    monkeypatch.setenv(CUDA_ROBOTS_ENV, "48")
    with pytest.raises(ValueError, match=CUDA_ROBOTS_ENV):
        resolve_schedule("auto", "cuda", 388)


@pytest.mark.reference
def test_block_of_lanes_per_robot_gives_the_same_bits_as_one_thread(precision="f64"):
    """The robots schedule's block (schedules.robot_steps): B lanes per robot, each striding over the robot's links
    and then its voxels, lane 0 the clock, the trace and rl4design's ω² max. On the CPU the lanes of a block run in
    turn: B = 3 (uneven strides; lanes idle on the robot of one voxel) gives the bits of B = 1, the CPU's schedule,
    over 60 steps of three bodies with rl4design's dt refresh and a trace sample every 7 steps — the GPU's partition
    of the work, without a GPU. (One precision and one B > 1: each is a kernel compiled cold in CI; B = 32 and f32
    passed too when this was written.)"""
    rng = np.random.default_rng(4)
    g = (rng.random((3, 4, 3, 3)) < 0.7).astype(np.uint8) * rng.integers(1, 4, size=(3, 4, 3, 3)).astype(np.uint8)
    g[:, 0, 0, 0] = 1
    g[2] = 0
    g[2, 1, 1, 1] = 2  # a robot of one voxel and no links
    cfg = short(precision=precision, semantics="rl4design")
    layout = Simulator(cfg, arch="cpu").layout(g)
    states = []
    for block_dim in (1, 3):
        eng = Engine(layout, cfg, arch="cpu", schedule="robots", block_dim=block_dim)
        eng.start_trace(7)
        eng.advance(33)
        eng.advance(27)
        assert (eng.robot_steps() == 60).all() and eng.block_dim == block_dim
        states.append([eng.voxel_state(), eng._table("lr"), eng.robot_dt(), eng._download("tr")])
    for other in states[1:]:
        for ours, theirs in zip(states[0], other, strict=True):
            np.testing.assert_array_equal(ours, theirs)


# ---------------------------------------------------------------- batching and robustness
def test_empty_single_and_all_empty_batches():
    g = np.zeros((3, 3, 3, 3), dtype=np.uint8)
    g[1, 1, 1, 1] = 1
    r = Simulator(short(), arch="cpu").simulate(torch.from_numpy(g))
    np.testing.assert_array_equal(r.simulated.numpy(), [False, True, False])
    assert r.displacement.shape == (3,) and r.displacement.dtype == torch.float32
    assert float(r.displacement[0]) == 0.0 and float(r.displacement[2]) == 0.0
    assert int(r.steps[0]) == 0 and int(r.steps[1]) > 0
    assert r.com_start.shape == (3, 3)
    r0 = Simulator(short(), arch="cpu").simulate(np.zeros((2, 4, 4, 4), np.uint8))
    assert not r0.simulated.any() and (r0.displacement == 0).all()
    r00 = Simulator(short(), arch="cpu").simulate(np.zeros((0, 4, 4, 4), np.uint8))
    assert r00.displacement.shape == (0,)


def test_batch_gives_each_robot_its_solo_result():
    rng = np.random.default_rng(1)
    g = (rng.random((4, 5, 4, 3)) < 0.6).astype(np.uint8) * rng.integers(1, 4, size=(4, 5, 4, 3)).astype(np.uint8)
    g[2] = 0
    g[3] = 0
    g[3, 2, 2, 1] = 2
    cfg = short(burn_in=0.02, duration=0.05)
    sim = Simulator(cfg, arch="cpu")
    batch = sim.simulate(g)
    for b in range(4):
        solo = sim.simulate(g[b:b + 1])
        np.testing.assert_array_equal(batch.com_end[b].numpy(), solo.com_end[0].numpy())
        np.testing.assert_array_equal(batch.max_voxel_displacement[b].numpy(), solo.max_voxel_displacement[0].numpy())
        assert int(batch.steps[b]) == int(solo.steps[0])


def test_robot_queue_spreads_robots_over_workers_without_changing_results():
    """The CPU schedule hands robots to worker threads through an atomic queue: every robot is run exactly once
    per launch (steps and time advance by the launch's steps), and 1, 2 or 5 workers give bit-identical states."""
    rng = np.random.default_rng(2)
    g = (rng.random((7, 4, 3, 3)) < 0.7).astype(np.uint8) * rng.integers(1, 4, size=(7, 4, 3, 3)).astype(np.uint8)
    g[:, 0, 0, 0] = 1
    sim = Simulator(short(), arch="cpu")
    states = []
    for workers in (1, 2, 5):
        eng = sim.engine(sim.layout(g))
        eng._workers = workers
        eng.advance(37)
        eng.advance(26)
        assert (eng.robot_steps() == 63).all()
        states.append((eng.positions(), eng.orientations()))
    for pos, ori in states[1:]:
        np.testing.assert_array_equal(pos, states[0][0])
        np.testing.assert_array_equal(ori, states[0][1])


def test_diverging_robot_is_flagged_and_others_go_on():
    g = np.zeros((2, 4, 4, 4), dtype=np.uint8)
    g[0] = 1  # a cube: unstable at this dt
    g[1, 0, 0, 0] = 1  # a lone voxel: stable
    r = Simulator(SimConfig(dt=1e-3, burn_in=0.05, duration=0.1), arch="cpu").simulate(g)
    np.testing.assert_array_equal(r.diverged.numpy(), [True, False])
    assert float(r.displacement[0]) == 0.0
    assert int(r.steps[1]) >= 150 and int(r.steps[0]) < 50  # the cube was stopped early, the voxel ran on
    for x in (r.displacement, r.com_start, r.com_end, r.max_voxel_displacement, r.com_displacement):
        assert torch.isfinite(x).all()


def test_com_reward_option_and_windows():
    g = np.zeros((1, 6, 3, 2), dtype=np.uint8)
    g[0, :3] = 2
    g[0, 3:] = 3
    cfg = short(reward="com", burn_in=0.25, duration=0.5)
    r = Simulator(cfg, arch="cpu").simulate(g)
    assert float(r.displacement[0]) == float(r.com_displacement[0])
    d = (r.com_end - r.com_start)[:, :2].norm(dim=1) / cfg.voxel_size
    np.testing.assert_allclose(r.com_displacement.numpy(), d.numpy(), rtol=1e-5)
    assert float(r.time[0]) > 0.75 and float(r.time[0]) < 0.75 + 2 * float(r.dt[0])


def test_recording_format():
    g = np.zeros((2, 3, 3, 3), dtype=np.uint8)
    g[0, :2, 0, 0] = [1, 2]
    cfg = short(burn_in=0.0, duration=0.01)
    r = Simulator(cfg, arch="cpu").simulate(g, record_every=20)
    rec = r.recording
    n_frames = len(rec.times)
    assert rec.times[0] == 0.0 and np.all(np.diff(rec.times) > 0)
    assert rec.voxel_size == cfg.voxel_size
    assert rec.positions[0].shape == (n_frames, 2, 3) and rec.positions[0].dtype == np.float32
    assert rec.orientations[0].shape == (n_frames, 2, 4)
    np.testing.assert_allclose(rec.orientations[0][0], [[1, 0, 0, 0]] * 2)
    np.testing.assert_array_equal(rec.lattice[0], [[0, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(rec.materials[0], [1, 2])
    assert rec.positions[1].shape == (n_frames, 0, 3)
    np.testing.assert_allclose(rec.positions[0][0], [[0, 0, 0], [0.01, 0, 0]])


# ---------------------------------------------------------------- GPU hardening, exercised on the CPU
def three_robots() -> np.ndarray:
    """Three small bodies with links (2×2×2 of materials 1, 2, 3): uint8 [3, 2, 2, 2]."""
    return np.stack([np.full((2, 2, 2), m, dtype=np.uint8) for m in (1, 2, 3)])


@pytest.mark.parametrize("schedule", ["robots", "flat"])
@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("where", ["velocity", "position"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_planted_nonfinite_state_diverges_its_robot_only(schedule, precision, where, value):
    """A NaN or an infinity planted in one voxel of robot 1 (an initial velocity: caught by the voxel update; a
    position: caught by the link update's strain) flags robot 1 DIVERGED; robots 0 and 2 run on bit for bit as
    without it. The check reads the float's exponent bits, which no fast-math assumption can fold away."""
    sim = Simulator(short(precision=precision), arch="cpu", schedule=schedule)
    g = three_robots()
    clean = sim.engine(sim.layout(g))
    clean.advance(20)
    clean_pos = clean.positions()
    layout = sim.layout(g)
    planted = int(layout.voxel_start[1]) + 3
    if where == "velocity":
        layout.velocity[planted, 0] = value
    eng = sim.engine(layout)
    if where == "position":
        vr = eng._table("vr")
        vr[VR.POS + 2, planted] = value
        eng._upload("vr", vr)
    eng.advance(20)
    np.testing.assert_array_equal(eng.robot_status(), [RUNNING, DIVERGED, RUNNING])
    others = layout.voxel_robot != 1
    np.testing.assert_array_equal(eng.positions()[others], clean_pos[others])
    assert eng.robot_steps()[1] < 20 and (eng.robot_steps()[[0, 2]] == 20).all()


def test_planted_nan_scores_zero_and_leaves_results_finite():
    sim = Simulator(short(), arch="cpu")
    layout = sim.layout(three_robots())
    layout.velocity[int(layout.voxel_start[1]), 2] = np.nan
    r = sim.run(layout)
    np.testing.assert_array_equal(r.diverged.numpy(), [False, True, False])
    assert float(r.displacement[1]) == 0.0 and not r.stalled.any()
    for x in (r.displacement, r.com_start, r.com_end, r.max_voxel_displacement, r.com_displacement):
        assert torch.isfinite(x).all()


@pytest.mark.parametrize("schedule", ["robots", "flat"])
def test_robot_whose_dynamic_dt_collapses_is_stalled_and_others_finish(schedule):
    """rl4design refreshes dt from the links' stiffness. Robot 1's material pair is made 30× stiffer after its
    initial dt was set (a planted stiffness, still stable at that dt for the 10 steps before the first refresh):
    its dt drops ~5.5×, so it would need ~5.5× the protocol's steps. It is stopped at SimConfig.step_cap (3) × those
    steps and flagged stalled (reward 0); robot 0 ends exactly as it does alone."""
    cfg = short(semantics="rl4design", burn_in=0.02, duration=0.03)
    sim = Simulator(cfg, arch="cpu", schedule=schedule)
    g = three_robots()[:2]
    solo = sim.simulate(g[:1])
    eng = sim.engine(sim.layout(g))
    lt = eng._table("lt")
    pair = 2 * (len(cfg.materials) + 1) + 2  # material 2 with material 2
    lt[LT.EHAT, pair] *= 30
    eng._upload("lt", lt)
    r = sim.finish(eng)
    np.testing.assert_array_equal(r.stalled.numpy(), [False, True])
    assert not r.diverged.any()
    assert int(r.steps[1]) == int(eng.max_steps[1])
    assert eng.max_steps[1] == np.ceil(cfg.step_cap * 0.05 / eng.dt0[1]) + 1
    assert float(r.time[1]) < 0.05 and float(r.displacement[1]) == 0.0
    assert eng.robot_dt()[1] < eng.dt0[1] / 4
    assert float(r.dt[0]) == float(solo.dt[0]) and int(r.steps[0]) == int(solo.steps[0])
    np.testing.assert_array_equal(r.com_end[0].numpy(), solo.com_end[0].numpy())
    np.testing.assert_array_equal(r.max_voxel_displacement[0].numpy(), solo.max_voxel_displacement[0].numpy())


@pytest.mark.parametrize("schedule", ["robots", "flat"])
def test_trace_of_a_robot_that_stops_first_is_its_solo_trace_then_its_end(schedule):
    """The kernels write each robot's trace samples as it steps (the batch is not stopped for them). With robot 1
    held up by the planted stiffness above (it runs 3× the steps), robot 0's trace in the batch is its trace alone
    up to its end, then its end repeated; robot 1 is sampled every k steps to its own end, where it is stalled."""
    cfg = short(semantics="rl4design", burn_in=0.02, duration=0.03)
    sim = Simulator(cfg, arch="cpu", schedule=schedule)
    g = three_robots()[:2]
    solo = sim.simulate(g[:1], trace_every=0.002).trace
    eng = sim.engine(sim.layout(g))
    lt = eng._table("lt")
    lt[LT.EHAT, 2 * (len(cfg.materials) + 1) + 2] *= 30
    eng._upload("lt", lt)
    r = sim.finish(eng, trace_every=0.002)
    tr, k = r.trace, r.trace.every
    assert k == solo.every and k > 1
    f0 = solo.time.shape[1]
    assert f0 == 1 + -(-int(r.steps[0]) // k) and tr.time.shape[1] == 1 + -(-int(r.steps[1]) // k) > 2 * f0
    for name in ("time", "com", "bbox_min", "bbox_max", "contacts", "orientation", "valid"):
        ours, alone = getattr(tr, name)[0], getattr(solo, name)[0]
        assert torch.equal(ours[:f0], alone), name
        assert torch.equal(ours[f0:], alone[-1:].expand_as(ours[f0:])), name
    assert (tr.time[1].diff() > 0).all() and bool(r.stalled[1])
    assert tr.valid[1, :-1].all() and not tr.valid[1, -1]  # stalled at its last step


@pytest.mark.parametrize("schedule", ["robots", "flat"])
def test_trace_of_a_diverging_robot_keeps_its_last_good_step_then_its_failed_one(schedule):
    """A trace sample every step (k = 1): the unstable cube's trace has every step it completed, valid, then one
    frame for the step that failed, invalid — what a batch stopped at every sample saw. (Its last good step is a
    frame, so the end-of-run summary must not overwrite it.)"""
    g = np.zeros((1, 4, 4, 4), np.uint8)
    g[0] = 1
    r = Simulator(SimConfig(dt=1e-3, burn_in=0.05, duration=0.1), arch="cpu", schedule=schedule).simulate(
        g, trace_every=1e-3)
    s, tr = int(r.steps[0]), r.trace
    assert bool(r.diverged[0]) and tr.every == 1 and 0 < s < 50
    assert tr.time.shape[1] == s + 2
    assert tr.valid[0, : s + 1].all() and not tr.valid[0, s + 1]
    np.testing.assert_allclose(tr.time[0, : s + 1].numpy(), np.arange(s + 1) * 1e-3, rtol=1e-12, atol=1e-15)
    assert torch.isfinite(tr.com[0, : s + 1]).all()


def test_start_trace_refuses_bad_intervals_and_a_started_engine():
    sim = Simulator(short(), arch="cpu")
    eng = sim.engine(sim.layout(three_robots()[:1]))
    with pytest.raises(ValueError, match="every"):
        eng.start_trace(0)
    with pytest.raises(RuntimeError, match="no trace"):
        eng.trace_frames()
    eng.advance(3)
    with pytest.raises(RuntimeError, match="before the first advance"):
        eng.start_trace(5)
    fresh = sim.engine(sim.layout(three_robots()[:1]))
    fresh.start_trace(5)
    fresh.advance(3)
    with pytest.raises(RuntimeError, match="still running"):
        fresh.trace_frames()


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_flat_schedule_through_a_compute_graph_equals_launches_from_python(precision):
    """The compute graph issues the same launches in the same order: the same bits, traces included, whether the
    steps fill whole graphs (and a remainder) or not."""
    g = np.zeros((3, 3, 2, 2), np.uint8)
    g[0, :, :, 0], g[0, :2, :, 1] = 2, 3
    g[1, :2, :2, :2] = 1
    g[2, :, 0, 0] = 3
    runs = [Simulator(short(precision=precision, graph_launches=k), arch="cpu", schedule="flat").simulate(
        g, trace_every=0.01) for k in (0, 3, 64)]
    for other in runs[1:]:
        for name in ("com_end", "displacement", "max_voxel_displacement", "steps"):
            np.testing.assert_array_equal(getattr(other, name).numpy(), getattr(runs[0], name).numpy(), err_msg=name)
        assert torch.equal(other.trace.com, runs[0].trace.com)
    assert (runs[0].trace.com[0, -1] - runs[0].trace.com[0, 0]).norm() > 1e-4  # it moved


def test_device_arrays_are_reused_across_batches():
    """A Simulator keeps one set of device arrays: a smaller batch reuses them (the same ndarray objects, nothing
    allocated: a 2,500-epoch run allocates nothing after its largest batch), results on reused arrays equal those
    on fresh ones bit for bit, and only a batch that outgrows them gets new ones."""
    rng = np.random.default_rng(3)
    g = (rng.random((6, 5, 4, 3)) < 0.6).astype(np.uint8) * rng.integers(1, 4, size=(6, 5, 4, 3)).astype(np.uint8)
    g[:, 0, 0, 0] = 1
    sim = Simulator(short(burn_in=0.01, duration=0.02), arch="cpu")
    sim.simulate(g)
    first, allocated = sim.arrays.arrays(), sim.arrays.allocations
    for batch in (g[3:5], g[:1], g[1:6], g[2:3]):
        reused = sim.simulate(batch)
        fresh = Simulator(sim.config, arch="cpu").simulate(batch)
        for name in ("displacement", "com_end", "steps", "dt"):
            np.testing.assert_array_equal(getattr(reused, name).numpy(), getattr(fresh, name).numpy())
    now = sim.arrays.arrays()
    assert sim.arrays.allocations == allocated and all(now[k] is a for k, a in first.items())
    sim.simulate(np.concatenate([g, g, g]))  # 3× the voxels, links and robots: outgrows every buffer
    grown = sim.arrays.arrays()
    assert sim.arrays.allocations > allocated
    for name in BUFFERS:  # each buffer holds per-item tables
        key = next(k for k in first if k[0] == name)
        assert grown[key] is not first[key], key


def test_engine_on_arrays_taken_over_refuses_to_run():
    sim = Simulator(short(), arch="cpu")
    layout = sim.layout(three_robots())
    old = sim.engine(layout)
    sim.engine(layout)
    with pytest.raises(RuntimeError, match="reused by a later Engine"):
        old.advance(1)
    with pytest.raises(RuntimeError, match="reused by a later Engine"):
        old.positions()
