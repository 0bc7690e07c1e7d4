"""Terrain in the simulator against analytic mechanics: Voxelyze's floor model (penalty, collision damping,
static/kinetic Coulomb friction) measured along the local surface normal. Passive bodies in f64, global damping off
where an analytic law is compared (it is a drag of ~49 /s on every voxel)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from freeform.sim import SimConfig, Simulator, Terrain
from freeform.sim.terrain import placement

L = 0.01
G = 9.81
M = 1500 * L**3  # voxel mass
KPEN = 2 * 1e5 * L  # 2·E·L


def cfg(terrain: Terrain, **kw) -> SimConfig:
    kw.setdefault("temp_amplitude", 0.0)
    kw.setdefault("dt", 1e-4)
    return SimConfig(precision="f64", terrain=terrain, **kw)


def engine(config: SimConfig, grids: np.ndarray, **hooks):
    sim = Simulator(config, arch="cpu")
    layout = sim.layout(grids)
    for name, value in hooks.items():
        getattr(layout, name)[...] = value
    return sim.engine(layout)


def block(*shape: int) -> np.ndarray:
    return np.ones((1, *shape), dtype=np.uint8)


def walker() -> np.ndarray:
    """An asymmetric muscle walker (tests/test_sim_physics.actuated_batch's first body) mirrored so that it walks
    towards +x on flat ground."""
    g = np.zeros((1, 8, 4, 4), dtype=np.uint8)
    g[0, :, :, :1] = 3
    g[0, :3, :, 1:3] = 2
    return np.ascontiguousarray(g[:, ::-1])


# ---------------------------------------------------------------- flat
def test_zero_heightmap_reproduces_the_flat_floor():
    """The general terrain path (normal, tangential projections, bilinear grid) on a zero height field gives
    Voxelyze's floor: same trajectory as the flat floor's own code to rounding, over a settling, sliding block."""
    g = block(2, 2, 2)
    vel = np.tile([0.2, 0.1, 0.0], (8, 1))
    ref = engine(cfg(Terrain.flat(), global_damping=0.0), g, velocity=vel)
    gen = engine(cfg(Terrain.heightmap(np.zeros((4, 3)), 0.05, x0=-0.1, y0=-0.1), global_damping=0.0), g,
                 velocity=vel)
    for _ in range(4):
        ref.advance(500)
        gen.advance(500)
        np.testing.assert_allclose(gen.positions(), ref.positions(), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(gen.static_friction(), ref.static_friction())
    assert ref.static_friction()[0::2].all()  # the bottom layer stopped by kinetic friction and sticks again


def test_flat_terrain_places_nothing():
    sim = Simulator(cfg(Terrain.flat()), arch="cpu")
    lay = sim.layout(np.ones((2, 2, 3, 2), np.uint8))
    off = placement(Terrain.flat(), Terrain.flat().field(L), lay.lattice, lay.voxel_robot, lay.num_robots, L)
    assert (off == 0).all()


# ---------------------------------------------------------------- slopes
@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 3, 2)])
def test_block_on_slope_below_friction_angle_stays(shape):
    """tan 20° = 0.36 < μk = 0.5 < μs = 1: after settling the block stays put (< 0.02 voxel over 1 s)."""
    eng = engine(cfg(Terrain.slope(20), global_damping=0.0), block(*shape))
    eng.advance(5000)  # 0.5 s: land, tip onto the slope, stick
    p0 = eng.positions().mean(axis=0)
    eng.advance(10000)
    drift = np.linalg.norm(eng.positions().mean(axis=0) - p0) / L
    assert drift < 0.02
    assert eng.static_friction().any()


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 2, 2)])
def test_block_on_slope_above_friction_angle_slides_at_coulomb_acceleration(shape):
    """tan 50° = 1.19 > μs = 1: the block slides down with a = g(sin θ − μk cos θ)."""
    theta = math.radians(50)
    eng = engine(cfg(Terrain.slope(50), global_damping=0.0), block(*shape))
    eng.advance(2000)
    v1, t1 = eng.velocities().mean(axis=0), eng.robot_time()[0]
    eng.advance(2000)
    v2, t2 = eng.velocities().mean(axis=0), eng.robot_time()[0]
    a = (v2 - v1) / (t2 - t1)
    expected = G * (math.sin(theta) - 0.5 * math.cos(theta))
    along = a[0] * -math.cos(theta) + a[2] * -math.sin(theta)  # down the slope (uphill is +x)
    assert along == pytest.approx(expected, rel=0.10)
    assert abs(a[1]) < 1e-6 and not eng.static_friction().any()
    # (the lone voxel, a point mass with Coulomb friction, is exact to rounding)
    if shape == (1, 1, 1):
        assert along == pytest.approx(expected, rel=1e-6)


def test_contact_normal_force_balances_weight_component():
    """A voxel at rest on a 20° slope: k·pen = m·g·cos θ, with pen measured along the normal."""
    theta = math.radians(20)
    eng = engine(cfg(Terrain.slope(20)), block(1, 1, 1))
    eng.advance(10000)
    x, _, z = eng.positions()[0]
    dist = (z - (math.tan(theta) * x - 0.5 * L)) * math.cos(theta)  # centre to plane
    pen = 0.5 * L - dist
    assert KPEN * pen == pytest.approx(M * G * math.cos(theta), rel=1e-6)
    assert np.abs(eng.velocities()).max() < 1e-9


def test_voxel_dropped_on_slope_comes_to_rest_on_it():
    """Thrown down onto a 20° slope at 0.3 m/s, a voxel bounces, sticks and rests at its static penetration."""
    theta = math.radians(20)
    eng = engine(cfg(Terrain.slope(20), global_damping=0.0), block(1, 1, 1), velocity=[[0.0, 0.0, -0.3]])
    eng.advance(2000)
    p0 = eng.positions()[0]
    eng.advance(5000)
    x, _, z = eng.positions()[0]
    assert np.linalg.norm(eng.positions()[0] - p0) < 1e-8  # at rest
    dist = (z - (math.tan(theta) * x - 0.5 * L)) * math.cos(theta)
    assert 0.5 * L - dist == pytest.approx(M * G * math.cos(theta) / KPEN, rel=1e-6)
    assert eng.static_friction()[0]


def test_walker_climbs_slope_more_slowly_than_it_walks_on_flat_ground():
    grounds = []

    def progress(terrain: Terrain) -> float:
        r = Simulator(SimConfig(burn_in=0.5, duration=1.0, terrain=terrain), arch="cpu").simulate(
            walker(), record_every=5000)
        assert not r.diverged.any()
        grounds.append(r.recording.ground)
        return float(r.com_end[0, 0] - r.com_start[0, 0]) / L

    flat, up = progress(Terrain.flat()), progress(Terrain.slope(5))
    assert flat > 0.3  # it walks (+x, voxel lengths in 1 s)
    assert 0 < up < 0.6 * flat
    # the recordings carry the ground for drawing: none for the flat floor, the slope's plane otherwise
    assert grounds[0] is None
    x = np.linspace(-0.1, 0.1, 7)
    np.testing.assert_allclose(grounds[1].height(x, 0 * x), math.tan(math.radians(5)) * x - 0.5 * L, atol=1e-15)


# ---------------------------------------------------------------- steps and columns
def test_block_rests_on_a_staircase_tread_at_its_height():
    """Steps 5 mm high: a block placed over the second tread (a columnar height field) rests at its height."""
    heights = [[0.0], [0.005], [0.010], [0.015]]
    eng = engine(cfg(Terrain.heightmap(heights, 0.03, x0=-0.04, smooth=False)), block(2, 2, 1))
    eng.advance(5000)
    z = eng.positions()[:, 2]
    # lowest voxel centre at the tread's surface (0.005 − L/2 + L/2), less its static sag m·g/k
    np.testing.assert_allclose(z, 0.005 - M * G / KPEN, rtol=0, atol=1e-9)


def test_block_is_stopped_by_a_riser_face():
    """A block slid along the floor into a 2 cm riser stops at its face (contact on the side, normal −x)."""
    eng = engine(cfg(Terrain.steps(0.02, 0.05, gap=0.01), global_damping=0.0), block(2, 2, 1))
    x_front0 = eng.positions()[:, 0].max() + 0.5 * L
    assert x_front0 == pytest.approx(-0.01)
    eng.advance(1000)
    vel = np.zeros((4, 3))
    vel[:, 0] = 0.5  # enough to cross the gap: v²/(2 μk g) = 2.5 cm
    eng.set_velocity(vel)
    fronts = []
    for _ in range(60):
        eng.advance(50)
        fronts.append(eng.positions()[:, 0].max() + 0.5 * L)
    # it reaches the riser at x = 0 (penetrating by < 1 mm at the impact), rebounds a little and stops short of it
    assert -0.0003 < max(fronts) < 0.001
    assert -0.005 < fronts[-1] < 0.0 and np.abs(eng.velocities()[:, 0]).max() < 1e-6
    assert eng.positions()[:, 2].max() < 0.002  # still on the floor, not on the step


def test_bodies_start_resting_on_the_steps_first_tread_gap():
    t = Terrain.steps(0.01, 0.03, gap=0.02)
    sim = Simulator(cfg(t), arch="cpu")
    g = np.zeros((2, 4, 2, 2), np.uint8)
    g[0, :2] = 1
    g[1] = 1
    eng = sim.engine(sim.layout(g))
    p = eng.positions()
    lay = eng.layout
    for r in range(2):
        mine = lay.voxel_robot == r
        assert p[mine, 0].max() + 0.5 * L == pytest.approx(-0.02)
        assert p[mine, 2].min() == pytest.approx(0.0)


def test_rough_ground_is_smooth_bounded_and_bodies_rest_on_it():
    t = Terrain.rough(0.004, 0.04, seed=3)
    f = t.field(L)
    xs = np.linspace(-0.2, 0.2, 401)
    h = f.height(xs, 0.0 * xs) + 0.5 * L
    assert np.abs(h).max() <= 0.004 + 1e-12 and h.std() > 0.0005
    assert np.abs(np.diff(h)).max() < 0.004 * 2 * math.pi / 0.04 * 1e-3 * 1.5  # |h'| ≤ 2πA/λ
    eng = engine(cfg(t), block(3, 3, 1))
    p = eng.positions()
    gap = p[:, 2] - f.support(p[:, 0], p[:, 1], 0.5 * L)
    assert gap.min() == pytest.approx(0.0, abs=1e-12)  # one voxel touches, none penetrates
    eng.advance(3000)
    assert np.isfinite(eng.positions()).all()


# ---------------------------------------------------------------- trace
def test_trace_of_free_fall_is_the_symplectic_sum():
    """Floor off: the trace's COM height at sample k (n = k·every steps) is −g·dt²·n(n+1)/2 exactly, and the
    box, contacts, orientation and times follow."""
    dt = 1e-4
    config = SimConfig(precision="f64", dt=dt, floor=False, global_damping=0.0, temp_amplitude=0.0, burn_in=0.01,
                       duration=0.02)
    r = Simulator(config, arch="cpu").simulate(block(2, 1, 1), trace_every=0.005)
    tr = r.trace
    assert tr.every == 50
    # samples every 50 steps from t = 0; the last is the robot's end (the first step past burn_in + duration)
    n = np.append(np.arange(tr.time.shape[1] - 1) * 50, 301)
    np.testing.assert_allclose(tr.time[0].numpy(), n * dt, rtol=1e-12)
    np.testing.assert_allclose(tr.com[0, :, 2].numpy(), -G * dt * dt * n * (n + 1) / 2, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(tr.com[0, :, 0].numpy(), 0.5 * L)
    np.testing.assert_allclose((tr.bbox_max - tr.bbox_min)[0, :, 0].numpy(), L)
    assert (tr.contacts == 0).all() and tr.valid.all() and tr.voxels.tolist() == [2.0]
    np.testing.assert_allclose(tr.orientation[0].numpy(), np.tile([1.0, 0, 0, 0], (len(n), 1)), atol=1e-12)
    assert int(tr.burn_in_end[0]) == 2 and tr.evaluation[0].sum() == len(n) - 3


def test_trace_counts_contacts_and_marks_empty_bodies():
    g = np.zeros((2, 3, 3, 2), np.uint8)
    g[0] = 1  # 9 voxels on the floor, 9 above
    r = Simulator(cfg(Terrain.flat(), burn_in=0.01, duration=0.01), arch="cpu").simulate(g, trace_every=0.005)
    tr = r.trace
    assert tr.contacts[0, 1:].tolist() == [9.0] * (tr.time.shape[1] - 1)
    assert not tr.valid[1].any() and (tr.com[1] == 0).all()
    np.testing.assert_allclose(tr.z_min[0, -1].item(), -M * G * 2 / KPEN, rtol=0.05)  # two layers' weight


@pytest.mark.parametrize("terrain", [Terrain.slope(10), Terrain.steps(0.004, 0.02)])
def test_schedules_agree_on_terrain(terrain):
    """The GPU's flat schedule (soa order) and the CPU's robots schedule run the same terrain contact."""
    g = np.zeros((2, 4, 3, 3), np.uint8)
    g[0, :, :, 0] = 2
    g[0, :2, :, 1] = 3
    g[1, :2, :2, :2] = 1
    config = SimConfig(precision="f64", terrain=terrain, burn_in=0.05, duration=0.1)
    a, b = (Simulator(config, arch="cpu", schedule=s).simulate(g, trace_every=0.05).trace for s in ("robots", "flat"))
    np.testing.assert_allclose(a.com.numpy(), b.com.numpy(), rtol=0, atol=1e-12)
    assert (a.com[0, -1] - a.com[0, 0]).norm() > 1e-4  # it moved: the comparison is not of two resting bodies
