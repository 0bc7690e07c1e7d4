"""The closed-loop control environment (freeform/envs/control.py): observations against hand-computed values,
the action mask, episodes, rewards against the simulated centre of mass, and refusals."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from freeform.envs import VecEnv
from freeform.envs.control import OBS_CHANNELS, ControlConfig, ControlEnv
from freeform.sim import SimConfig, Simulator
from freeform.sim.config import material_table
from freeform.sim.state import MT, RT, VR

C = {name: i for i, name in enumerate(OBS_CHANNELS)}


def pair() -> np.ndarray:
    """One body: a muscle (material 2) at cell (1, 2, 0) and a passive voxel (1) at (2, 2, 0) of a 3³ grid."""
    g = np.zeros((1, 3, 3, 3), np.uint8)
    g[0, 1, 2, 0], g[0, 2, 2, 0] = 2, 1
    return g


def test_first_observation_of_a_two_voxel_body_by_hand():
    cfg = SimConfig(precision="f64")
    env = ControlEnv(pair(), sim=cfg, control=ControlConfig(burn_in=0.0, duration=0.05))
    assert isinstance(env, VecEnv)
    obs = env.reset()
    # the box: the body cropped to its bounding box, 2 × 1 × 1 cells, starting at grid cell (1, 2, 0)
    assert env.box == (2, 1, 1) and env.origin.tolist() == [[1, 2, 0]]
    assert obs.shape == (1, len(OBS_CHANNELS), 2, 1, 1) and obs.dtype == torch.float32
    L, k = cfg.voxel_size, len(cfg.materials)
    m = material_table(cfg)[MT.MASS]
    com_x = (m[2] * 0.0 + m[1] * L) / (m[2] + m[1])  # the cropped body: the muscle at x = 0, the passive at x = L
    for cell, mat, x in (((0, 0, 0), 2, 0.0), ((1, 0, 0), 1, L)):
        o = obs[0, :, cell[0], cell[1], cell[2]].double()
        assert o[C["filled"]] == 1 and o[C["material"]] == pytest.approx(mat / k)
        assert o[C["actuated"]] == (1 if mat == 2 else 0)
        assert o[C["rel_x"]] == pytest.approx((x - com_x) / L, abs=1e-6)
        assert o[C["rel_y"]] == 0 and o[C["rel_z"]] == 0
        assert o[C["vel_x"]] == 0 and o[C["strain"]] == 0 and o[C["contact"]] == 0
        assert o[C["heading_cos"]] == 1 and o[C["heading_sin"]] == 0 and o[C["progress"]] == 0
        assert o[C["clock_sin"]] == 0 and o[C["clock_cos"]] == 1  # t = 0: the sine's phase 0
    assert env.action_mask.tolist() == [[True, False]]  # only the muscle's command acts
    grid = env.to_grid(torch.tensor([[0.5, -0.25]]))  # back on the body's own 3³ grid
    assert grid[0, 1, 2, 0] == 0.5 and grid[0, 2, 2, 0] == -0.25 and grid.abs().sum() == 0.75


def test_rewards_sum_to_the_displacement_along_the_heading_and_episodes_end_together():
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    control = ControlConfig(burn_in=0.01, duration=0.05, headings="random")
    env = ControlEnv(g, sim=SimConfig(precision="f64"), control=control, seed=3)
    env.reset()
    heading, start = env.heading.copy(), env._com.copy()
    rng = torch.Generator().manual_seed(0)
    total = torch.zeros(2, dtype=torch.float64)
    assert env.box == (3, 3, 3)  # the full body's box (the pair's fits in it: empty cells are zero)
    for t in range(control.steps):
        obs, reward, done, info = env.step(torch.rand((2, 27), generator=rng) * 2 - 1)
        total += reward.double()
        assert done.all() == (t == control.steps - 1)
        if t < control.steps - 1:
            end = env._com.copy()
    assert info["truncated"].all() and info["final_obs"].shape == obs.shape
    assert (obs[:, C["progress"]] == 0).all()  # reset: the next episode's first observation
    # the rewards telescope: all but the last step's sum to the centre of mass's move along the heading until then
    expected = ((end - start)[:, 0] * np.cos(heading) + (end - start)[:, 1] * np.sin(heading)) / env.sim_config.voxel_size
    assert np.abs(expected).max() > 1e-4  # the random commands moved the bodies
    np.testing.assert_allclose(total.numpy() - reward.double().numpy(), expected, rtol=1e-5, atol=1e-9)


def test_refusals_name_the_problem():
    with pytest.raises(ValueError, match="at least one voxel"):
        ControlEnv(np.zeros((1, 3, 3, 3), np.uint8))
    with pytest.raises(ValueError, match="ρ"):
        ControlEnv(np.ones((1, 3, 3, 2), np.uint8))
    with pytest.raises(ValueError, match="control.period"):
        ControlEnv(pair(), control=ControlConfig(period=0.0))
    with pytest.raises(ValueError, match="headings"):
        ControlEnv(pair(), control=ControlConfig(headings="north"))
    env = ControlEnv(pair(), control=ControlConfig(burn_in=0.0, duration=0.02))
    with pytest.raises(RuntimeError, match="reset"):
        env.step(torch.zeros(1, 2))
    env.reset()
    with pytest.raises(ValueError, match=r"one per cell of the bodies' box \(2, 1, 1\)"):
        env.step(torch.zeros(1, 3))
    with pytest.raises(ValueError, match="finite"):
        env.step(torch.full((1, 2), math.nan))
    g = np.concatenate([pair(), np.zeros((1, 3, 3, 3), np.uint8)])
    g[1, 0, 0, 0] = 2  # a one-voxel body in a box of 2 × 1 × 1: its second cell is empty
    env = ControlEnv(g, control=ControlConfig(burn_in=0.0, duration=0.02))
    env.reset()
    env.step(torch.tensor([[0.0, 0.0], [0.0, math.nan]]))  # NaN in an empty cell: ignored


def test_every_episode_starts_from_the_settled_state_of_a_fresh_env():
    """The first episode settles the bodies and snapshots them; later episodes restore that state. A second episode
    equals a fresh env's first, observation for observation and reward for reward, under the same actions."""
    control = ControlConfig(burn_in=0.05, duration=0.0375)
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    actions = [torch.rand((2, 27), generator=torch.Generator().manual_seed(t)) * 2 - 1 for t in range(control.steps)]

    def episode(env: ControlEnv, first: torch.Tensor) -> list[torch.Tensor]:
        seen = [first]
        for a in actions:
            obs, reward, done, info = env.step(a)
            seen += [info.get("final_obs", obs), reward]
        return seen

    reused = ControlEnv(g, sim=SimConfig(precision="f64"), control=control)
    episode(reused, reused.reset())  # its first episode; the env then reset itself (restored the settled state)
    second = episode(reused, reused._observe()[0])
    fresh = ControlEnv(g, sim=SimConfig(precision="f64"), control=control)
    expected = episode(fresh, fresh.reset())
    for a, b in zip(second, expected, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("headings, residual", [("random", True), ("any", True), ("random", False)])
def test_a_snapshot_mid_episode_replays_its_future_bit_for_bit_after_another_branch(headings, residual):
    """``snapshot`` then ``restore``: whatever was played in between (another branch of actions), the same actions
    from the restored state give the same observations and rewards, to the bit — under everything that carries
    state from step to step (bandwidth, ramps, residual strokes, the sensed response, the privileged critic)."""
    control = ControlConfig(burn_in=0.05, period=0.025, duration=0.2, headings=headings, command_rate=26.0,
                            residual=residual, ramp=True, stroke_periods=2, response=True, privileged_critic=True)
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    env = ControlEnv(g, sim=SimConfig(precision="f64"), control=control, seed=3)
    rng = torch.Generator().manual_seed(0)
    draw = [torch.rand((2, env.action_dim), generator=rng) * 4 - 2 for _ in range(3)]
    other = [torch.rand((2, env.action_dim), generator=rng) * 4 - 2 for _ in range(control.steps + 1)]

    def future(actions: list[torch.Tensor]) -> list[torch.Tensor]:
        seen = []
        for a in actions:
            obs, reward, _, info = env.step(a)
            seen += [obs["policy"], obs["critic"], reward, info["heading"]]
        return seen

    env.reset()
    env.step(draw[0])
    snap = env.snapshot()
    first = [env.observation["policy"].clone()]
    expected = future(draw[1:])
    assert env.t != snap["env"]["t"]  # (the branch moved on: not a no-op)
    env.restore(snap)
    future(other)  # another branch from the same state, past the episode's end to another clock than the snapshot's
    assert env.episode == snap["env"]["episode"] + 1 and env.t != snap["env"]["t"]
    replayed = [env.restore(snap)["policy"]] + future(draw[1:])
    assert len(replayed) == len(expected) + 1
    for a, b in zip(replayed, first + expected, strict=True):
        assert torch.equal(a, b)
    with pytest.raises(RuntimeError, match="reset"):
        ControlEnv(g, sim=SimConfig(precision="f64"), control=control).snapshot()


def test_a_command_rate_limits_each_steps_change():
    """``command_rate`` r: each step's command moves towards the action by at most r·period (here 0.25 of the full
    range per step), so a step from 0 to 1 takes four steps; without it the command is the action at once."""
    control = ControlConfig(burn_in=0.0, duration=0.0625, command_rate=20.0)  # 20 /s · 0.0125 s = 0.25 per step
    env = ControlEnv(pair(), sim=SimConfig(precision="f64"), control=control)
    env.reset()
    muscle = env.layout.material == 2
    seen = []
    for action in (1.0, 1.0, -1.0, 1.0):
        env.step(torch.full((1, 2), action))
        seen.append(float(env.engine._table("vr")[VR.CMD][muscle][0]))
    assert seen == pytest.approx([0.25, 0.5, 0.25, 0.5])
    free = ControlEnv(pair(), sim=SimConfig(precision="f64"), control=ControlConfig(burn_in=0.0, duration=0.05))
    free.reset()
    free.step(torch.full((1, 2), 0.7))
    assert float(free.engine._table("vr")[VR.CMD][free.layout.material == 2][0]) == pytest.approx(0.7)
    with pytest.raises(ValueError, match="command_rate"):
        ControlEnv(pair(), control=ControlConfig(command_rate=0.0))


def test_residual_control_with_zero_actions_is_the_open_loop_gait_bit_for_bit():
    """``residual``: the bodies walk their open-loop sine from t = 0 (burn-in included), corrected by the actions; with
    zero actions they are where an open-loop engine puts them after the same time, to the bit (f64). The last
    channel is each muscle's sine sin(2π(t/T + φ)) mid-way through the coming period, by hand."""
    control = ControlConfig(burn_in=0.025, duration=0.05, headings="any", residual=True)
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    cfg = SimConfig(precision="f64")
    env = ControlEnv(g, sim=cfg, control=control)
    assert env.channels == (*OBS_CHANNELS, "open_loop") and env.observation_shape == (17, 3, 3, 3)
    assert env.sim_config.actuation == "residual"
    # the default materials: 1 passive, 2 a muscle at phase 0, 3 one at phase 0.5 (cycles); the box holds the pair's
    # muscle at cell 0 and its passive voxel at cell 1, the cube's 27 muscles everywhere
    phase = torch.tensor([[0.0], [0.5]], dtype=torch.float64)
    muscle = env.action_mask
    assert muscle.sum(1).tolist() == [1, 27] and bool(muscle[0, 0])
    obs = env.reset()
    for t in range(control.steps):
        middle = (control.burn_in + (t + 0.5) * control.period) / cfg.temp_period
        expected = torch.where(muscle, torch.sin(2 * math.pi * (middle + phase)), 0.0)
        assert torch.equal(obs[:, -1].reshape(2, -1), expected.float())
        if t < control.steps - 1:
            obs, *_ = env.step(torch.zeros(2, 27))
    open_loop = Simulator(replace(env.sim_config, actuation="sine"), arch="cpu")
    engine = open_loop.engine(open_loop.layout(env.grids))
    engine.advance_time(control.burn_in)
    for _ in range(control.steps - 1):
        engine.advance_time(control.period)
    np.testing.assert_array_equal(env.engine.positions(), engine.positions())
    assert np.abs(engine.positions() - env.layout.lattice * cfg.voxel_size).max() > 1e-4  # they walked
    # a correction of +2 (actions are clipped there) drives every muscle to the top of its range at any phase
    env.step(torch.zeros(2, 27))  # (the episode's last step: the env resets itself)
    env.step(torch.full((2, 27), 5.0))
    assert np.all(env.engine._table("vr")[VR.CMD][np.isin(env.layout.material, (2, 3))] == 2.0)


def test_a_state_saved_before_a_config_field_existed_loads_with_its_default():
    env = ControlEnv(pair(), sim=SimConfig(precision="f64"), control=ControlConfig(burn_in=0.0, duration=0.025))
    env.reset()
    state = env.state_dict()
    del state["config"]["control"]["residual"]  # a checkpoint from before residual control
    env.load_state_dict(state)
    other = ControlEnv(pair(), control=ControlConfig(burn_in=0.0, duration=0.025, residual=True))
    with pytest.raises(ValueError, match="does not match"):
        other.load_state_dict(state)
    with pytest.raises(ValueError, match="control.residual"):
        ControlConfig(residual="yes").validate()


def test_headings_any_rewards_the_growth_of_the_distance_from_the_start_in_the_plane():
    """``headings="any"`` (the paper's locomotion reward for a controller): the return is the centre of mass's
    distance in the ground plane from where the episode started, whichever way the body went; no heading is seen."""
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    control = ControlConfig(burn_in=0.01, duration=0.05, headings="any")
    env = ControlEnv(g, sim=SimConfig(precision="f64"), control=control)
    obs = env.reset()
    start = env._com.copy()
    assert float(obs[:, C["heading_cos"]].abs().max()) == 0 and float(obs[:, C["heading_sin"]].abs().max()) == 0
    rng = torch.Generator().manual_seed(1)
    total = np.zeros(2)
    for _ in range(control.steps - 1):
        _, reward, _, _ = env.step(torch.rand((2, 27), generator=rng) * 2 - 1)
        total += reward.double().numpy()
    distance = np.hypot(*(env._com - start)[:, :2].T) / env.sim_config.voxel_size
    assert distance.min() > 1e-4 and np.all(total > 0)
    np.testing.assert_allclose(total, distance, rtol=1e-5, atol=1e-9)


def test_ramped_commands_reach_the_action_by_the_period_end():
    """``ramp``: the env hands each period's commands to the engine as a ramp over the period; the commands in force
    at its end are the actions, and a zero ramp of zero actions changes nothing (the open-loop case above)."""
    control = ControlConfig(burn_in=0.0, duration=0.05, ramp=True)
    env = ControlEnv(pair(), sim=SimConfig(precision="f64"), control=control)
    env.reset()
    env.step(torch.tensor([[0.6, 0.0]]))
    env.step(torch.tensor([[-0.4, 0.0]]))
    vr, muscle = env.engine._table("vr"), env.layout.material == 2
    assert float(vr[VR.CMD][muscle][0]) == pytest.approx(-0.4) and float(vr[VR.CMD0][muscle][0]) == pytest.approx(0.6)
    assert float(env.engine._table("rt")[RT.RAMP][0]) == control.period
    with pytest.raises(ValueError, match="control.ramp"):
        ControlConfig(ramp=1).validate()


def test_the_privileged_critic_sees_the_displacement_the_orientation_and_the_time_left():
    """``privileged_critic``: the observation's groups; the critic's state is the displacement since the episode's
    start (against the env's own centre of mass), an orientation recovered exactly from voxel offsets rotated by a
    known rotation (scipy's, the independent truth) and the fraction of the episode left."""
    from scipy.spatial.transform import Rotation

    from freeform.envs.control import CRITIC_STATE
    from freeform.sim.state import SENSE

    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    control = ControlConfig(burn_in=0.01, duration=0.05, headings="any", privileged_critic=True)
    env = ControlEnv(g, sim=SimConfig(precision="f64"), control=control)
    assert env.observation_shape == {"policy": (len(OBS_CHANNELS), 3, 3, 3), "critic": (len(CRITIC_STATE),)}
    obs = env.reset()
    plain = ControlEnv(g, sim=SimConfig(precision="f64"), control=replace(control, privileged_critic=False)).reset()
    assert torch.equal(obs["policy"], plain)  # the actor sees what it would without the critic's group
    critic = obs["critic"].double().numpy()
    assert critic.shape == (2, 10) and np.all(critic[:, :3] == 0) and np.all(critic[:, 9] == 1.0)
    np.testing.assert_allclose(critic[1, 3:9], [1, 0, 0, 0, 1, 0], atol=0.02)  # the settled cube, upright
    start = env._com.copy()
    for step in range(1, 3):
        obs, _, _, _ = env.step(torch.full((2, 27), 0.5))
        critic = obs["critic"].double().numpy()
        np.testing.assert_allclose(critic[:, :3], (env._com - start) / env.sim_config.voxel_size, rtol=1e-5, atol=1e-7)
        assert critic[0, 9] == pytest.approx(1 - step / control.steps)
    truth = Rotation.random(2, random_state=0).as_matrix()
    sensed = np.zeros((env.layout.num_voxels, SENSE.width))
    rotated = np.einsum("vij,vj->vi", truth[env._robot], env._rest) * env.sim_config.voxel_size
    sensed[:, SENSE.span("REL")] = rotated
    recovered = env._critic_state(sensed, env._com).double().numpy()[:, 3:9]
    np.testing.assert_allclose(recovered[1], np.concatenate([truth[1][:, 0], truth[1][:, 1]]), atol=1e-6)  # the cube


@pytest.mark.parametrize("residual", [False, True])
def test_a_stroke_plays_a_sin_plus_b_cos_of_each_voxels_own_phase_for_its_periods(residual):
    """``stroke_periods = 3``: one action (a, b) per cell is, bit for bit, three period steps whose commands are
    a·sin θ + b·cos θ, θ = 2π(t/T + φ) at each period's middle (computed here from the materials' phases); the
    rewards telescope to the same moves; under residual control zero strokes are the open-loop gait."""
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    control = ControlConfig(burn_in=0.01, period=0.01, duration=0.06, headings="fixed", residual=residual,
                            ramp=True, command_rate=30.0)
    sim = SimConfig(precision="f64")
    strokes = ControlEnv(g, sim=sim, control=replace(control, stroke_periods=3))
    periods = ControlEnv(g, sim=sim, control=control)
    assert strokes.action_dim == 2 * 27 and strokes.control.steps == 2 and periods.control.steps == 6
    strokes.reset(), periods.reset()
    phase = {m.phase for m in sim.materials}
    assert len(phase) > 1  # (the two muscles differ in phase: each voxel's own θ matters)
    cell_phase = torch.zeros(2, 27, dtype=torch.float64)
    for body in range(2):
        for cell in range(27):
            material = int(g[body].reshape(-1)[cell])
            cell_phase[body, cell] = sim.materials[material - 1].phase if material else 0.0
    rng = torch.Generator().manual_seed(2)
    total_strokes, total_periods = 0.0, 0.0
    for step in range(2):
        a, b = (torch.rand((2, 27), generator=rng, dtype=torch.float64) - 0.5 for _ in range(2))
        _, reward, _, _ = strokes.step(torch.cat([a, b], 1))
        total_strokes = total_strokes + reward.double()
        for k in range(3):
            middle = (control.burn_in + (3 * step + k + 0.5) * control.period) / sim.temp_period
            theta = 2 * math.pi * (middle + cell_phase)
            _, reward, _, _ = periods.step(a * torch.sin(theta) + b * torch.cos(theta))
            total_periods = total_periods + reward.double()
        np.testing.assert_array_equal(strokes.engine.positions(), periods.engine.positions())
    torch.testing.assert_close(total_strokes, total_periods, rtol=1e-6, atol=1e-9)
    if residual:  # zero strokes: the open-loop gait, as zero commands
        strokes.reset(), periods.reset()
        strokes.step(torch.zeros(2, 54))
        for _ in range(3):
            periods.step(torch.zeros(2, 27))
        np.testing.assert_array_equal(strokes.engine.positions(), periods.engine.positions())
    with pytest.raises(ValueError, match=r"a stroke's \(a, b\) per cell"):
        strokes.step(torch.zeros(2, 27))


def _turned(v: torch.Tensor, heading: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Planar vectors ``v [N, 2, ...]`` written in a frame turned about z by +heading (x along it), by hand."""
    c = torch.from_numpy(np.cos(heading)).double().view(-1, *[1] * (v.dim() - 2))
    s = torch.from_numpy(np.sin(heading)).double().view(-1, *[1] * (v.dim() - 2))
    x, y = v[:, 0].double(), v[:, 1].double()
    return c * x + s * y, c * y - s * x


def test_the_heading_frame_writes_every_planar_vector_along_the_heading():
    """``frame="heading"``: the same episode as the world frame (the frame is what is observed, not what is
    simulated: equal rewards), with the positions, velocities, responses and the privileged critic's displacement
    and body axes turned by minus each robot's heading (a rotation written out here), the heading channels 0, and
    every other channel unchanged."""
    g = np.concatenate([pair(), np.full((1, 3, 3, 3), 3, np.uint8)])
    control = ControlConfig(burn_in=0.01, duration=0.0375, headings="random", response=True, privileged_critic=True)
    world = ControlEnv(g, sim=SimConfig(precision="f64"), control=control, seed=0)
    turned = ControlEnv(g, sim=SimConfig(precision="f64"), control=replace(control, frame="heading"), seed=0)
    channels = {name: i for i, name in enumerate(world.channels)}
    pairs = [("rel_x", "rel_y"), ("vel_x", "vel_y"), ("resp_x_sin", "resp_y_sin"), ("resp_x_cos", "resp_y_cos")]
    a, b = world.reset(), turned.reset()
    for step in range(control.steps + 1):  # (the last step's observation is the next episode's first: new headings)
        heading = world.heading.copy()
        assert np.array_equal(heading, turned.heading) and np.ptp(heading) > 0.1  # (two different headings)
        wp, tp = a["policy"], b["policy"]
        moved = [channels[c] for p in pairs for c in p] + [channels["heading_cos"], channels["heading_sin"]]
        same = [i for i in range(len(world.channels)) if i not in moved]
        assert torch.equal(wp[:, same], tp[:, same])
        assert (tp[:, [channels["heading_cos"], channels["heading_sin"]]] == 0).all()
        for x, y in pairs:
            ex, ey = _turned(wp[:, [channels[x], channels[y]]], heading)
            assert ex.abs().max() + ey.abs().max() > 0 or x.startswith("vel")  # (something to turn)
            torch.testing.assert_close(tp[:, channels[x]].double(), ex, rtol=0, atol=1e-6)
            torch.testing.assert_close(tp[:, channels[y]].double(), ey, rtol=0, atol=1e-6)
        for x in (0, 3, 6):  # the critic's displacement and the body's x and y axes, in the ground plane
            ex, ey = _turned(a["critic"][:, x: x + 2, None], heading)
            torch.testing.assert_close(b["critic"][:, x: x + 2].double(), torch.cat([ex, ey], 1), rtol=0, atol=1e-6)
        if step == control.steps:
            break
        act = torch.rand((2, 27), generator=torch.Generator().manual_seed(step)) * 2 - 1
        (a, ra, _, _), (b, rb, _, _) = world.step(act), turned.step(act)
        assert torch.equal(ra, rb)
    with pytest.raises(ValueError, match="control.frame must be one of"):
        ControlEnv(pair(), control=ControlConfig(frame="body"))


def test_a_wave_head_travels_along_the_heading_in_either_frame(tmp_path, caplog):
    """The hand-set wave (a wave head whose learnt parts are 0) asks each voxel the same strokes whether the
    observation is in the world's frame (the wave vector turned by the heading channels) or in the heading's (the
    wave along x): the heading's frame changes what a controller reads, not the wave it starts from. A world
    frame's wave head is not saved as a heading frame's controller (its wave would read zeroed channels)."""
    import logging

    from freeform.agents.controller_file import save_controller
    from freeform.agents.networks.controllers import build_controller
    from freeform.run.build import load_controller

    g = np.concatenate([np.full((1, 3, 3, 3), 2, np.uint8), np.full((1, 3, 3, 3), 3, np.uint8)])
    g[0, 0] = 1
    control = ControlConfig(burn_in=0.01, duration=0.05, headings="random", residual=True, stroke_periods=2)
    means = []
    for frame in ("world", "heading"):
        env = ControlEnv(g, sim=SimConfig(precision="f64"), control=replace(control, frame=frame), seed=2)
        torch.manual_seed(0)
        net = build_controller("attention", env, hidden=8, head="wave")
        assert ("heading_channels" in net.wave) == (frame == "world")
        with torch.no_grad():
            for layer in (net.actor, net.wave_k):
                layer.weight.zero_()
                layer.bias.zero_()
            means.append(net(env.reset())[0])
            if frame == "world":
                net.wave_k.weight.add_(0.5)  # (something to load: the saved weights differ from a fresh net's)
                world_wave_k = net.wave_k.weight.clone()
        if frame == "world":
            with pytest.raises(ValueError, match="turns with the heading channels, which the heading's frame zeroes"):
                save_controller(tmp_path / "controller.pt", net, replace(control, frame="heading"))
            assert not (tmp_path / "controller.pt").exists()
            save_controller(tmp_path / "world" / "controller.pt", net, env.control)
        else:
            with pytest.raises(ValueError, match="runs along x whatever the heading"):
                save_controller(tmp_path / "controller.pt", net, replace(control, frame="world"))
            assert not (tmp_path / "controller.pt").exists()
            with caplog.at_level(logging.WARNING, logger="freeform.run.build"):  # a start from the other frame
                load_controller(net, str(tmp_path / "world"), frame="heading")
            assert "trained on observations in the world frame" in caplog.text
            torch.testing.assert_close(net.wave_k.weight, world_wave_k)  # (its weights, loaded)
    assert means[0].abs().max() > 0.1
    torch.testing.assert_close(means[1], means[0], rtol=0, atol=1e-5)
