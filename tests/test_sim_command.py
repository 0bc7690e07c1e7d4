"""Commanded actuation (``SimConfig(actuation="command")``, ``Engine.set_commands``): closed-loop control's way into
the simulator. The physics must be the open-loop physics with the sine replaced by the command, nothing else."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from freeform.sim import SimConfig, Simulator, runtime
from freeform.sim.config import material_table
from freeform.sim.state import CONTACT, DONE, MT, RT, RUNNING, SENSE, VI, VR


def bodies() -> np.ndarray:
    """Two small bodies with muscles of both phases (materials 2, 3) and passive voxels (1)."""
    g = np.zeros((2, 3, 3, 2), np.uint8)
    g[0, :, :, 0] = 1
    g[0, 0, :, 1], g[0, 2, :, 1] = 2, 3
    g[1, :2, :, :] = 3
    g[1, 2, :, 0] = 2
    return g


@pytest.mark.reference
@pytest.mark.parametrize("semantics", ["voxelyze", "rl4design"])
@pytest.mark.slow
def test_commands_equal_to_the_clock_term_reproduce_the_open_loop_gait_bit_for_bit(semantics):
    """Each step's command = the kernels' own clock term (the robot's sin/cos of the coming temperature's time, in
    the same angle-addition form as ``voxels.temperature``), from the same initial rest sizes: after 0.5 s (two
    periods of the sine: every muscle through both signs) the poses equal an open-loop engine's to the bit (f64,
    strict path). The loop's cost is Python's, a step at a time; 1 s doubled it and added no new phase."""
    cfg = SimConfig(precision="f64", semantics=semantics, burn_in=0.0, duration=0.5)
    sim_o, sim_c = Simulator(cfg, arch="cpu"), Simulator(replace(cfg, actuation="command"), arch="cpu")
    open_loop, commanded = sim_o.engine(sim_o.layout(bodies())), sim_c.engine(sim_c.layout(bodies()))
    vr = commanded._table("vr")
    vr[VR.SIZE] = open_loop._table("vr")[VR.SIZE]  # the sine's rest size at t = 0 (commands start at 0)
    commanded._upload("vr", vr)
    layout = commanded.layout
    mt = material_table(cfg)
    cos_phi, sin_phi = mt[MT.COSPHI][layout.material], mt[MT.SINPHI][layout.material]
    robot = layout.voxel_robot
    steps = 0
    while (commanded.robot_status() == RUNNING).any():  # every robot stops once past t = 0.5 s (its own dt)
        for _ in range(16):  # (a stopped robot stays as it stopped: steps past its end change nothing, either side)
            rt = commanded._table("rt")
            commanded.set_commands(rt[RT.SIN][robot] * cos_phi + rt[RT.COS][robot] * sin_phi)
            commanded.advance(1)
            steps += 1
    open_loop.advance(steps)
    assert (commanded.robot_time() >= 0.5).all()  # half a second of gait: two periods of the sine
    np.testing.assert_array_equal(commanded.positions(), open_loop.positions())
    np.testing.assert_array_equal(commanded.orientations(), open_loop.orientations())
    assert np.abs(open_loop.positions() - sim_o.layout(bodies()).lattice * cfg.voxel_size).max() > 1e-4  # it moved


def test_zero_commands_are_a_passive_body():
    """Commands start at 0: T = T_base, the rest size L, as the same body with no actuation amplitude."""
    cfg = SimConfig(precision="f64", burn_in=0.0, duration=0.2)
    still = Simulator(replace(cfg, temp_amplitude=0.0), arch="cpu").simulate(bodies())
    commanded = Simulator(replace(cfg, actuation="command"), arch="cpu").simulate(bodies())
    np.testing.assert_array_equal(commanded.com_end.numpy(), still.com_end.numpy())
    np.testing.assert_array_equal(commanded.max_voxel_displacement.numpy(), still.max_voxel_displacement.numpy())


def test_a_command_sets_the_rest_size_of_spec_section_4():
    """A constant command c: each muscle's rest size after a step is L·(1 + (T_base + A·c)·CTE), a passive
    voxel's stays L."""
    cfg = SimConfig(precision="f64", actuation="command", burn_in=0.0, duration=0.1)
    sim = Simulator(cfg, arch="cpu")
    engine = sim.engine(sim.layout(bodies()))
    c = np.linspace(-1.0, 1.0, engine.layout.num_voxels)
    engine.set_commands(c)
    engine.advance(1)
    mt = material_table(cfg)
    mat = engine.layout.material
    expected = mt[MT.L][mat] * (1.0 + (0.0 + cfg.temp_amplitude * c) * mt[MT.CTE][mat])
    np.testing.assert_allclose(engine.voxel_state()[VR.SIZE], expected, rtol=1e-15)
    assert (mt[MT.CTE][mat] == 0).any() and (mt[MT.CTE][mat] != 0).any()  # both kinds are in the bodies


@pytest.mark.reference
@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_residual_actuation_with_zero_commands_is_the_open_loop_gait_bit_for_bit(precision):
    """``actuation="residual"``: the kernels' sine plus a command of 0 — after 0.5 s the same poses as open loop."""
    cfg = SimConfig(precision=precision, burn_in=0.0, duration=0.5)
    results = [Simulator(replace(cfg, actuation=a), arch="cpu").simulate(bodies()) for a in ("sine", "residual")]
    np.testing.assert_array_equal(results[0].com_end.numpy(), results[1].com_end.numpy())
    np.testing.assert_array_equal(results[0].max_voxel_displacement.numpy(), results[1].max_voxel_displacement.numpy())


def test_a_residual_command_corrects_the_sine_within_its_range():
    """Residual actuation: T = T_base + A·clip(sine + c, −1, 1) — with the sine at its step-0 phase, commands of
    ±2 give the range's ends and a command c in between the sine plus c (spec section 4's rest size)."""
    cfg = SimConfig(precision="f64", actuation="residual", burn_in=0.0, duration=0.1)
    sim = Simulator(cfg, arch="cpu")
    engine = sim.engine(sim.layout(bodies()))
    layout, mt = engine.layout, material_table(cfg)
    n = layout.num_voxels
    c = np.where(np.arange(n) % 3 == 0, 2.0, np.where(np.arange(n) % 3 == 1, -2.0, 0.3))
    rt = engine._table("rt")
    robot, mat = layout.voxel_robot, layout.material
    sine = rt[RT.SIN][robot] * mt[MT.COSPHI][mat] + rt[RT.COS][robot] * mt[MT.SINPHI][mat]  # the coming step's
    engine.set_commands(c)
    engine.advance(1)
    wave = np.clip(sine + c, -1.0, 1.0)
    expected = mt[MT.L][mat] * (1.0 + (0.0 + cfg.temp_amplitude * wave) * mt[MT.CTE][mat])
    np.testing.assert_allclose(engine.voxel_state()[VR.SIZE], expected, rtol=1e-15)
    assert np.abs(wave).max() == 1.0 and (np.abs(wave) < 1).any()  # both the clip and the sum are exercised


@pytest.mark.parametrize("actuation", ["command", "residual"])
def test_a_ramped_command_moves_linearly_to_the_new_one_by_the_period_end(actuation):
    """``set_commands(c, ramp=p)`` then ``advance_time(p)``: each step's command is c₀ + (c − c₀)·(1 − (limit − τ)/p),
    τ the time of the step's temperature, c₀ the command before — spec section 4's rest size at every step, by hand;
    by the period's end it is c, as a jump would have it."""
    cfg = SimConfig(precision="f64", actuation=actuation, burn_in=0.0, duration=0.1)
    sim = Simulator(cfg, arch="cpu")
    engine = sim.engine(sim.layout(bodies()))
    layout, mt = engine.layout, material_table(cfg)
    robot, mat = layout.voxel_robot, layout.material
    n = layout.num_voxels
    before, after = np.linspace(-1.0, 1.0, n), np.linspace(0.8, -0.6, n)
    engine.set_commands(before)
    engine.advance_time(0.001)
    period = 0.002
    engine.set_commands(after, ramp=period)
    limit = engine._limit + period
    engine._write_column("rt", RT.UNTIL, limit)  # (what advance_time writes; here stepped one step at a time)
    seen = 0
    while True:
        rt = engine._table("rt")
        if not (rt[RT.T] < limit).any():
            break
        tau = (rt[RT.T] + rt[RT.DT])[robot]  # Voxelyze's temperature time: the step's end
        frac = np.clip(1.0 - (limit[robot] - tau) / period, 0.0, 1.0)
        c = before + (after - before) * frac
        if actuation == "residual":
            c = np.clip(rt[RT.SIN][robot] * mt[MT.COSPHI][mat] + rt[RT.COS][robot] * mt[MT.SINPHI][mat] + c, -1.0, 1.0)
        engine._advance(1)
        expected = mt[MT.L][mat] * (1.0 + cfg.temp_amplitude * c * mt[MT.CTE][mat])
        np.testing.assert_allclose(engine.voxel_state()[VR.SIZE], expected, rtol=1e-14)
        seen += bool(((frac > 0.1) & (frac < 0.9)).any())
    assert seen >= 3  # several steps mid-ramp
    np.testing.assert_array_equal(engine._table("vr")[VR.CMD], after)
    assert engine.robot_steps().min() > 0
    with pytest.raises(ValueError, match="ramp"):
        engine.set_commands(after, ramp=-1.0)


def test_bad_commands_are_refused_with_the_reason():
    sim = Simulator(SimConfig(duration=0.1), arch="cpu")
    with pytest.raises(RuntimeError, match="actuation='command'"):
        sim.engine(sim.layout(bodies())).set_commands(np.zeros(1))
    sim = Simulator(SimConfig(duration=0.1, actuation="command"), arch="cpu")
    engine = sim.engine(sim.layout(bodies()))
    with pytest.raises(ValueError, match="one per voxel"):
        engine.set_commands(np.zeros(engine.layout.num_voxels + 1))
    with pytest.raises(ValueError, match="finite"):
        engine.set_commands(np.full(engine.layout.num_voxels, np.nan))
    with pytest.raises(ValueError, match="sim.actuation"):
        SimConfig(actuation="clock").validate("sim")


def test_advance_time_runs_each_robot_past_its_own_control_times_and_changes_no_bit():
    """Under rl4design's dynamic dt every robot has its own step: advance_time(p) k times leaves each robot's
    clock past k·p by less than its last step, and each robot's state equals its solo run of the same steps with
    the same commands, to the bit (stopping and going does not touch the physics)."""
    cfg = SimConfig(precision="f64", semantics="rl4design", burn_in=0.0, duration=1.0, actuation="command")
    sim = Simulator(cfg, arch="cpu")
    engine = sim.engine(sim.layout(bodies()))
    period, square = 0.0125, [0.3 * (-1) ** k for k in range(4)]  # a square wave of commands
    counts = []
    for k, c in enumerate(square):
        engine.set_commands(np.full(engine.layout.num_voxels, c))
        engine.advance_time(period)
        counts.append(engine.robot_steps().copy())
        rt = engine._table("rt")
        limit = period * (k + 1)
        assert (rt[RT.T] >= limit - 1e-12).all() and (rt[RT.T] - rt[RT.DTPREV] < limit).all()
    assert counts[-1][0] != counts[-1][1]
    for r in range(2):
        solo_sim = Simulator(cfg, arch="cpu")
        solo = solo_sim.engine(solo_sim.layout(bodies()[r:r + 1]))
        done = 0
        for k, c in enumerate(square):
            solo.set_commands(np.full(solo.layout.num_voxels, c))
            solo.advance(int(counts[k][r]) - done)
            done = int(counts[k][r])
        lo, hi = engine.layout.voxel_start[r], engine.layout.voxel_start[r + 1]
        np.testing.assert_array_equal(solo.positions(), engine.positions()[lo:hi])
    with pytest.raises(ValueError, match="> 0"):
        engine.advance_time(0.0)


@pytest.mark.parametrize("schedule", ["robots", "flat"])
def test_sensing_on_the_device_equals_the_tables_read_back(schedule):
    """Engine.sense (one kernel) against the same quantities computed on the host from the engine's tables:
    centres of mass, positions relative to them, velocities, mean |strain| over each voxel's links, contact."""
    cfg = SimConfig(precision="f64", actuation="command", burn_in=0.0, duration=0.5)
    sim = Simulator(cfg, arch="cpu", schedule=schedule)
    engine = sim.engine(sim.layout(bodies()))
    engine.set_commands(np.random.default_rng(2).uniform(-1, 1, engine.layout.num_voxels))
    engine.advance(300)
    sensed, com, time, status = engine.sense()
    lay = engine.layout
    np.testing.assert_array_equal(time, engine.robot_time())
    np.testing.assert_array_equal(status, engine.robot_status())
    mass = material_table(cfg)[MT.MASS][lay.material]
    pos, vel = engine.positions(), engine.velocities()
    expect_com = np.stack([np.bincount(lay.voxel_robot, weights=mass * pos[:, k]) for k in range(3)], 1)
    expect_com /= np.bincount(lay.voxel_robot, weights=mass)[:, None]
    np.testing.assert_allclose(com, expect_com, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sensed[:, SENSE.span("REL")], pos - expect_com[lay.voxel_robot], atol=1e-14)
    np.testing.assert_allclose(sensed[:, SENSE.span("VEL")], vel, rtol=1e-12, atol=1e-15)
    strain = np.abs(engine.link_strain())
    slots = lay.slots
    mean = np.array([strain[s[s >= 0]].mean() if (s >= 0).any() else 0.0 for s in slots])
    np.testing.assert_allclose(sensed[:, SENSE.STRAIN], mean, rtol=1e-12, atol=1e-15)
    assert mean.max() > 0
    contact = (engine._table("vi")[VI.FLAGS] & CONTACT) != 0
    np.testing.assert_array_equal(sensed[:, SENSE.CONTACT], contact.astype(float))
    assert contact.any() and not contact.all()


@pytest.mark.parametrize("schedule", ["robots", "flat"])
def test_a_snapshot_restored_goes_on_bit_for_bit(schedule):
    """advance 0.05 s, snapshot, advance with commands → X; restore, the same again → X to the bit (f64), with the
    control limit (``advance_time``'s host copy) restored too — also into a fresh engine of the same layout after a
    larger batch grew the simulator's buffers (a population env's cohorts); a snapshot of another batch is
    refused."""
    cfg = SimConfig(precision="f64", burn_in=0.0, duration=1.0, actuation="command")
    sim = Simulator(cfg, arch="cpu", schedule=schedule)
    engine = sim.engine(sim.layout(bodies()))
    engine.advance_time(0.05)
    snap, at_snapshot = engine.snapshot(), engine.positions()
    commands = np.linspace(-1, 1, engine.layout.num_voxels)

    def go_on() -> tuple[np.ndarray, ...]:
        engine.set_commands(commands)
        engine.advance_time(0.02)
        return engine.positions(), engine.orientations(), engine.robot_time(), engine.sense().com

    first = go_on()
    assert np.abs(first[0] - at_snapshot).max() > 1e-6  # the bodies moved after the snapshot
    engine.restore(snap)
    for a, b in zip(go_on(), first, strict=True):
        np.testing.assert_array_equal(a, b)
    sim.engine(sim.layout(np.concatenate([bodies()] * 8)))  # a larger batch grows the simulator's buffers
    engine = sim.engine(sim.layout(bodies()))  # a fresh engine of the snapshot's layout takes it back
    assert any(engine._buffers[n].shape[0] > snap["buffers"][n].shape[0] for n in snap["buffers"])
    engine.restore(snap)
    for a, b in zip(go_on(), first, strict=True):
        np.testing.assert_array_equal(a, b)
    other = Simulator(cfg, arch="cpu", schedule=schedule)
    big = other.engine(other.layout(np.concatenate([bodies()] * 40)))
    with pytest.raises(ValueError, match="restore a snapshot of this engine"):
        big.restore(snap)


@pytest.mark.parametrize("schedule, graph", [("robots", 64), ("flat", 64), ("flat", 0)])
@pytest.mark.parametrize("semantics, actuation, ramp", [("voxelyze", "command", 0.0), ("rl4design", "residual", 1.0)])
def test_a_control_step_in_one_call_equals_commands_advance_time_and_sense_bit_for_bit(schedule, graph, semantics,
                                                                                        actuation, ramp):
    """Engine.control_step(c, p, ramp) against set_commands(c, ramp) + advance_time(p) + sense(), period after
    period (f64): the same readout, the same limits and every buffer the same to the bit — after a settling
    advance_time (as the control env's burn-in), ramps included, under rl4design's dynamic dt (each robot its own
    steps), across a free advance() (the next period starts at the clocks again) and past the robots' end (DONE:
    nothing left to step). On the flat schedule with and without its compute graph (graph_launches 0: the
    launches from Python, quadrants' way); a graph that fails to build would warn, and warnings fail here."""
    cfg = SimConfig(precision="f64", semantics=semantics, burn_in=0.0, duration=0.07, actuation=actuation,
                    graph_launches=graph)
    two = [Simulator(cfg, arch="cpu", schedule=schedule) for _ in range(2)]
    stepwise, one_call = (sim.engine(sim.layout(bodies())) for sim in two)
    rng, period = np.random.default_rng(3), 0.0125
    statuses = []
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for engine in (stepwise, one_call):
            engine.advance_time(0.01)
        for k in range(7):
            if k == 3:
                stepwise.advance(7)
                one_call.advance(7)
            c = rng.uniform(-1, 1, stepwise.layout.num_voxels)
            stepwise.set_commands(c, ramp=ramp * period)
            stepwise.advance_time(period)
            expect, got = stepwise.sense(), one_call.control_step(c, period, ramp=ramp * period)
            for name, a, b in zip(expect._fields, expect, got, strict=True):
                np.testing.assert_array_equal(b, a, err_msg=f"period {k}: readout.{name}")
            np.testing.assert_array_equal(one_call._limit, stepwise._limit, err_msg=f"period {k}: limits")
            for name, a in stepwise.snapshot()["buffers"].items():
                np.testing.assert_array_equal(one_call.snapshot()["buffers"][name], a, err_msg=f"period {k}: {name}")
            statuses.append(got.status.copy())
    assert (statuses[0] == RUNNING).all() and (statuses[-1] == DONE).all()


def test_a_control_step_is_one_call_to_the_device():
    """With every other kernel taken away, control_step still runs a period: on the robots schedule it is one
    kernel, on the flat one a compute graph (where the backend has graphs: Taichi's)."""
    from types import SimpleNamespace

    cfg = SimConfig(precision="f32", burn_in=0.0, duration=1.0, actuation="command")
    for schedule, keep in (("robots", "control_robots"), ("flat", "control_graph")):
        sim = Simulator(cfg, arch="cpu", schedule=schedule)
        engine = sim.engine(sim.layout(bodies()))
        if schedule == "flat" and not hasattr(runtime.ti.graph, "GraphBuilder"):
            continue  # (quadrants: no compute graphs, the step is three launches and the steps')
        engine.control_step(np.zeros(engine.layout.num_voxels), 0.01)  # (the first step reads the clocks)

        def refused(*args, **kwargs):
            raise AssertionError("a control step launched a kernel of its own")

        engine.kernels = SimpleNamespace(**{name: (value if name == keep else refused)
                                            for name, value in vars(engine.kernels).items()})
        engine._transfers = SimpleNamespace(read=refused, write=refused)
        readout = engine.control_step(np.full(engine.layout.num_voxels, 0.5), 0.01)
        assert (readout.time >= 0.02).all() and (readout.time < 0.02 + 1e-3).all(), (schedule, readout.time)
