"""The physics engine against independent truth: spec `physics.md` section 15 (Voxelyze, built and run by the
spec's authors), analytic mechanics, and a float64 run of the same engine where f32 precision matters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from freeform.sim import Material, SimConfig, Simulator

L = 0.01
REC = 1.240490e-4  # VX recommendedTimeStep, ν = 0.35
REC_NU0 = 1.949242e-4  # ν = 0 (and a lone voxel)
G = 9.81


def body(shape: tuple[int, int, int], mat: int = 1) -> np.ndarray:
    return np.full((1, *shape), mat, dtype=np.uint8)


def engine(cfg: SimConfig, grids: np.ndarray, **hooks):
    sim = Simulator(cfg, arch="cpu")
    layout = sim.layout(grids)
    for name, value in hooks.items():
        getattr(layout, name)[...] = value
    return sim.engine(layout)


def f64(**kw) -> SimConfig:
    kw.setdefault("temp_amplitude", 0.0)
    return SimConfig(precision="f64", **kw)


# ---------------------------------------------------------------- spec section 15 reference traces
@pytest.mark.reference
def test_single_voxel_settles_like_voxelyze():
    eng = engine(f64(dt=REC_NU0), body((1, 1, 1)))
    z = []
    for _ in range(5):
        eng.advance(1)
        z.append(eng.positions()[0, 2])
    ref = [-3.727353e-07, -1.000847e-06, -1.785046e-06, -2.644365e-06, -3.515425e-06]
    np.testing.assert_allclose(z, ref, rtol=2e-6)
    eng.advance(400)
    m = 1500 * L**3
    np.testing.assert_allclose(eng.positions()[0, 2], -m * G / (2 * 1e5 * L), rtol=1e-6)  # −m·g/(2EL)
    np.testing.assert_allclose(eng.positions()[0, 2], -7.357501e-06, rtol=1e-6)


@pytest.mark.reference
def test_heated_pair_matches_voxelyze_trace():
    cfg = f64(dt=REC, gravity=0.0, floor=False, materials=[Material(cte=0.01)])
    temp = np.array([0.0, 10.0])
    eng = engine(cfg, body((2, 1, 1)), temp_base=temp)
    x = []
    for i in range(3):
        eng.advance(1)
        x.append(eng.positions()[0, 0])
        if i == 0:
            np.testing.assert_allclose(eng.link_strain(), [-4.761906e-02], rtol=1e-6)
    # VX keeps strain in float: agreement to ~4e-7 relative
    np.testing.assert_allclose(x, [-7.840332e-06, -2.163924e-05, -3.972073e-05], rtol=2e-6)
    eng.advance(6000)
    p = eng.positions()
    np.testing.assert_allclose(p[1, 0] - p[0, 0], 1.05e-2, rtol=1e-6)


@pytest.mark.reference
@pytest.mark.parametrize(
    "nb, nu, dt, tip_z, tip_dx, angle",
    [
        (5, 0.35, REC, -7.467345e-03, -7.737548e-04, 0.259997),
        (5, 0.0, REC_NU0, -7.467671e-03, -7.717357e-04, 0.259997),
        (10, 0.35, REC, -7.093677e-02, -4.204202e-02, 1.251602),
    ],
)
def test_cantilever_matches_voxelyze(nb, nu, dt, tip_z, tip_dx, angle):
    cfg = f64(dt=dt, floor=False, materials=[Material(poisson=nu)])
    fixed = np.zeros(nb, dtype=bool)
    fixed[0] = True
    eng = engine(cfg, body((nb, 1, 1)), fixed=fixed)
    eng.advance(int(round(3.0 / dt)))
    p, q = eng.positions()[-1], eng.orientations()[-1]
    np.testing.assert_allclose(p[2], tip_z, rtol=1e-5)
    np.testing.assert_allclose(p[0] - (nb - 1) * L, tip_dx, rtol=1e-5)
    np.testing.assert_allclose(2 * math.acos(min(1.0, abs(q[0]))), angle, rtol=1e-5)
    # the root stays put
    np.testing.assert_array_equal(eng.positions()[0], [0.0, 0.0, 0.0])


@pytest.mark.reference
@pytest.mark.parametrize(
    "n, dt, com_dz, lowest",
    [
        (4, REC, -7.004900e-05, -3.0899e-05),
        (4, 1.18e-4, -7.004908e-05, -3.0899e-05),
        (8, REC, -2.796796e-04, -7.4568e-05),
        (10, 1.18e-4, -4.359864e-04, -9.7042e-05),
    ],
)
def test_cube_settling_matches_voxelyze(n, dt, com_dz, lowest):
    eng = engine(f64(dt=dt), body((n, n, n)))
    z0 = eng.positions()[:, 2].mean()
    eng.advance(math.ceil(0.5 / dt))  # VX's harness steps while t < 0.5 s
    z = eng.positions()[:, 2]
    # Static friction locks in the path of the transient, so the settled state carries VX's float rounding:
    # N ≤ 8 agrees to ~1e-6 relative, N = 10 to ~3e-4 (COM) and ~1.2e-3 (lowest voxel, at dt = 1.18e-4).
    np.testing.assert_allclose(z.mean() - z0, com_dz, rtol=5e-4 if n == 10 else 2e-5)
    np.testing.assert_allclose(z.min(), lowest, rtol=2e-3 if n == 10 else 2e-4)


# ---------------------------------------------------------------- analytic mechanics
def test_free_fall_matches_analytic():
    """No floor, no damping: symplectic Euler gives z_n = −g·dt²·n(n+1)/2, within O(dt) of −g t²/2."""
    dt = 1e-4
    eng = engine(f64(dt=dt, floor=False, global_damping=0.0), body((2, 2, 2)))
    n = 2000
    eng.advance(n)
    z = eng.positions()[:, 2] - np.array([0, 1, 0, 1, 0, 1, 0, 1]) * L
    t = n * dt
    np.testing.assert_allclose(z, -G * dt * dt * n * (n + 1) / 2, rtol=1e-9)
    np.testing.assert_allclose(z, -G * t * t / 2, rtol=1.0 / n + 1e-9)


def test_free_fall_with_global_damping_matches_ode():
    """m z'' = −m g − c z' with c = ζ_g·2√(mEL): z = −(g/γ)t + (g/γ²)(1 − e^{−γt}), γ = c/m."""
    dt = 2e-5
    eng = engine(f64(dt=dt, floor=False), body((1, 1, 1)))
    n = 10000
    eng.advance(n)
    m = 1500 * L**3
    gamma = 0.03 * 2 * math.sqrt(m * 1e5 * L) / m
    t = n * dt
    exact = -(G / gamma) * t + (G / gamma**2) * (1 - math.exp(-gamma * t))
    np.testing.assert_allclose(eng.positions()[0, 2], exact, rtol=2e-3)


def test_linear_momentum_conserved_without_gravity_and_floor():
    rng = np.random.default_rng(0)
    grid = np.zeros((1, 4, 3, 3), dtype=np.uint8)
    grid[0, :, 1, 1] = 1
    grid[0, 1, :, :] = 2
    grid[0, 3, 0, 0:2] = 3
    n = int((grid > 0).sum())
    vel = rng.normal(0, 0.05, size=(n, 3))
    cfg = f64(dt=1e-4, gravity=0.0, floor=False, global_damping=0.0, temp_amplitude=10.0)
    eng = engine(cfg, grid, velocity=vel)
    p0 = vel.sum(axis=0)
    eng.advance(3000)
    p1 = eng.velocities().sum(axis=0)  # equal masses: Σ v ∝ momentum
    assert np.abs(eng.positions()).max() < 1.0
    np.testing.assert_allclose(p1, p0, atol=1e-10)


def test_sliding_block_stops_after_kinetic_friction_distance():
    """A settled 2×2×1 block launched at v0 slides v0²/(2 μk g) (global damping off)."""
    cfg = f64(dt=1e-4, global_damping=0.0)
    eng = engine(cfg, body((2, 2, 1)))
    eng.advance(2000)  # settle onto the floor
    x0 = eng.positions()[:, 0].copy()
    v0 = 0.3
    vel = np.zeros((4, 3))
    vel[:, 0] = v0
    eng.set_velocity(vel + eng.velocities() * [0, 0, 1])
    eng.advance(int(0.2 / 1e-4))
    d = eng.positions()[:, 0] - x0
    assert np.all(eng.static_friction())  # it has stopped and re-entered static friction
    np.testing.assert_allclose(d, v0**2 / (2 * 0.5 * G), rtol=0.02)
    assert np.abs(eng.velocities()[:, 0]).max() == 0.0


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_passive_body_at_rest_stays_at_rest(precision):
    grid = np.zeros((1, 4, 3, 3), dtype=np.uint8)
    grid[0, :, :, 0] = 1
    grid[0, 0, :, 1:] = 1
    cfg = SimConfig(precision=precision, burn_in=0.0, duration=5.0)
    r = Simulator(cfg, arch="cpu").simulate(grid)
    assert not r.diverged.any()
    assert float(r.max_voxel_displacement[0]) < 0.01
    assert float(r.time[0]) > 5.0


@pytest.mark.parametrize("phase", [0.0, 0.5])
def test_free_muscle_pair_follows_actuation(phase):
    """Two free muscle voxels: their separation tracks L·(1 + 0.1·sin 2π(t/0.25 + φ)) (quasi-static, ω ≪ ω_link).
    φ = 0.5 cycles (muscle B) is the case that catches a phase in the wrong unit (π·φ instead of 2π·φ: a quarter
    period off); φ = 0 cannot."""
    cfg = SimConfig(precision="f64", gravity=0.0, floor=False, materials=[Material(cte=0.01, phase=phase)],
                    burn_in=0.0, duration=0.5)
    r = Simulator(cfg, arch="cpu").simulate(body((2, 1, 1)), record_every=40)
    rec = r.recording
    sep = rec.positions[0][:, 1, 0] - rec.positions[0][:, 0, 0]
    t = rec.times
    target = L * (1 + 0.1 * np.sin(2 * np.pi * (t / cfg.temp_period + phase)))
    # skip the first period's transient; the link lags its rest length by a few steps
    late = t > 0.25
    np.testing.assert_allclose(sep[late], target[late], atol=2e-3 * L)
    assert sep.max() > 1.09 * L and sep.min() < 0.91 * L


# ---------------------------------------------------------------- precision, schedules, semantics
def actuated_batch() -> np.ndarray:
    g = np.zeros((3, 8, 4, 4), dtype=np.uint8)
    g[0, :, :, :1] = 3
    g[0, :3, :, 1:3] = 2  # asymmetric: muscle B floor layer, muscle A block at one end
    g[1, :, :, :2] = 1  # passive slab
    g[2, :4, :2, :2] = 2
    g[2, 4:, :2, :2] = 3
    return g


def test_actuated_asymmetric_robot_moves_and_passive_does_not():
    r = Simulator(SimConfig(burn_in=0.5, duration=1.0), arch="cpu").simulate(actuated_batch())
    assert float(r.displacement[0]) > 0.2  # voxel lengths in 1 s
    assert float(r.displacement[1]) < 1e-3
    assert not r.diverged.any()


def test_f32_agrees_with_f64():
    g = actuated_batch()
    res = {p: Simulator(SimConfig(precision=p, burn_in=0.5, duration=1.0), arch="cpu").simulate(g)
           for p in ("f32", "f64")}
    a, b = res["f32"].displacement, res["f64"].displacement
    np.testing.assert_allclose(a[[0, 2]].numpy(), b[[0, 2]].numpy(), rtol=0.03)
    np.testing.assert_allclose(res["f32"].com_end.numpy(), res["f64"].com_end.numpy(), atol=1e-4)


@pytest.mark.parametrize("swap", ["xy", "xz"])
def test_mirrored_body_moves_as_the_body_mirrored(swap):
    """The asymmetric walker mirrored by swapping x and y (on the floor, under gravity) or x and z (free: no
    gravity, no floor) moves as the walker itself, mirrored: its x links become y (or z) links with the same
    negative and positive ends, so each axis's compiled copy of the link frame's permutations (links.py) is held
    against another's. The two bodies' arithmetic differs only in order (rounding), where a wrong sign or swap in
    one axis's copy moves voxels by ~1e-4 m. (A quarter turn is no test: it swaps the ends of half the links,
    and Voxelyze's beam, whose frame is the negative end's, is not symmetric under that beyond first order.)"""
    M = np.array({"xy": [[0, 1, 0], [1, 0, 0], [0, 0, 1]], "xz": [[0, 0, 1], [0, 1, 0], [1, 0, 0]]}[swap])
    a = actuated_batch()[0]
    cells = np.argwhere(a > 0)
    turned = cells @ M.T
    turned -= turned.min(0)
    grids = np.zeros((2, 8, 8, 8), dtype=np.uint8)
    grids[0][tuple(cells.T)] = a[tuple(cells.T)]
    grids[1][tuple(turned.T)] = a[tuple(cells.T)]
    cfg = f64(temp_amplitude=10.0) if swap == "xy" else f64(temp_amplitude=10.0, gravity=0.0, floor=False)
    eng = engine(cfg, grids)
    lay = eng.layout
    start = eng.positions()
    eng.advance(400)
    moved = eng.positions() - start
    where = {tuple(c): i for i, c in enumerate(lay.lattice) if lay.voxel_robot[i] == 1}
    shift = (lay.lattice[lay.voxel_robot == 0] @ M.T).min(0)
    pairs = np.array([(i, where[tuple(c @ M.T - shift)]) for i, c in enumerate(lay.lattice)
                      if lay.voxel_robot[i] == 0])
    assert len(pairs) == len(cells) and np.abs(moved).max() > 1e-4
    np.testing.assert_allclose(moved[pairs[:, 1]], moved[pairs[:, 0]] @ M.T, rtol=0, atol=1e-10)


@pytest.mark.reference
def test_schedules_agree_exactly_in_f64():
    """The two schedules are two compiled kernels of the same functions: on the strict path, the same bits. (With
    fast-math each compiler may reassociate each kernel its own way: quadrants' LLVM 22 then moved the passive
    slab's max displacement, a difference of nearly equal positions, by 2e-10 voxel lengths.)"""
    cfg = SimConfig(precision="f64", burn_in=0.05, duration=0.1)
    g = actuated_batch()
    a = Simulator(cfg, arch="cpu", schedule="robots").simulate(g)
    b = Simulator(cfg, arch="cpu", schedule="flat").simulate(g)
    np.testing.assert_array_equal(a.com_end.numpy(), b.com_end.numpy())
    np.testing.assert_array_equal(a.max_voxel_displacement.numpy(), b.max_voxel_displacement.numpy())


def test_rl4design_rest_length_uses_negative_voxel():
    """rl4design's L0 = size of the negative voxel: heating the negative end stretches the pair by 10 %,
    heating the positive end does nothing; VX stretches both by 5 %."""
    for heated, sem, expect in [(0, "rl4design", 1.10), (1, "rl4design", 1.0), (0, "voxelyze", 1.05),
                                (1, "voxelyze", 1.05)]:
        cfg = SimConfig(precision="f64", dt=REC, gravity=0.0, floor=False, temp_amplitude=0.0,
                        materials=[Material(cte=0.01)], semantics=sem)
        temp = np.zeros(2)
        temp[heated] = 10.0
        eng = engine(cfg, body((2, 1, 1)), temp_base=temp)
        eng.advance(6000)
        p = eng.positions()
        np.testing.assert_allclose(p[1, 0] - p[0, 0], expect * L, rtol=1e-5, err_msg=f"{sem} heated={heated}")


def test_rl4design_initial_static_flag_and_dynamic_dt():
    g = actuated_batch()[:1]
    vx = Simulator(SimConfig(precision="f64"), arch="cpu").engine(Simulator().layout(g))
    ifx = Simulator(SimConfig(precision="f64", semantics="rl4design"), arch="cpu").engine(Simulator().layout(g))
    assert vx.static_friction().all() and not ifx.static_friction().any()
    dt0 = ifx.robot_dt()[0]
    ifx.advance(400)  # muscles now contracted/extended: the refreshed dt differs from the initial one
    assert ifx.robot_dt()[0] != dt0
    vx.advance(400)
    assert vx.robot_dt()[0] == dt0
