"""A control env over a stream of bodies (``freeform.envs.PopulationControlEnv``, issue 42) and a muscle's bandwidth
on what a muscle receives: the stream is a function of the episode count, a cohort drawn again starts from the
state it settled to (bit for bit a fresh env's), ranks hold slices of the same bodies, a run resumes bit for bit,
and under residual control the bandwidth limits the sine plus the correction."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import straight_and_resumed

from freeform.checkpoint import load_checkpoint
from freeform.config import compose
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.envs.population import DesignBodies, PopulationControlEnv, Stream, design_cohort
from freeform.records import read_record
from freeform.sim import SimConfig

SIZES = DesignBodies(resolution=6, materials=4, steps=6, bundle_size=2)
SIM = SimConfig(burn_in=0.0, precision="f64")
SHORT = ControlConfig(burn_in=0.02, duration=0.025, headings="any", residual=True, ramp=True)


def test_cohorts_are_fresh_non_empty_bodies_and_a_function_of_their_index() -> None:
    a, b = design_cohort(SIZES, 8, 0, 0), design_cohort(SIZES, 8, 0, 1)
    assert a.shape == (8, 6, 6, 6) and a.dtype == torch.uint8
    assert (a.flatten(1) > 0).any(1).all() and (b.flatten(1) > 0).any(1).all()
    assert torch.equal(a, design_cohort(SIZES, 8, 0, 0))  # the same cohort, drawn again
    assert not torch.equal(a, b) and not torch.equal(a, design_cohort(SIZES, 8, 1, 0))  # another cohort, stream


def test_the_pool_slides_along_the_stream_and_a_redrawn_cohort_restores_its_settled_state() -> None:
    env = PopulationControlEnv(SIZES, Stream(4, pool=2, refresh_every=2), sim=SIM, control=SHORT, seed=5)
    seen: dict[int, torch.Tensor] = {}
    obs = env.reset()
    for episode in range(8):
        c = env.cohort_at(episode)
        assert episode // 2 <= c < episode // 2 + 2 and env.current is env._cohorts[c]
        assert set(env._cohorts) <= {episode // 2 - 1, *range(episode // 2, episode // 2 + 2)}  # the old ones go
        if c in seen:  # drawn again: the settled state restored, not settled anew
            assert torch.equal(obs, seen[c])
        seen[c], grids = obs, env.grids
        for _ in range(SHORT.steps):
            obs, _, done, info = env.step(torch.zeros(4, env.action_dim))
        assert done.all() and torch.equal(info["final_grids"], grids)  # (the episode's records: its own bodies)
    assert len(seen) >= 4  # (eight episodes, a new cohort every two)
    fresh = ControlEnv(design_cohort(SIZES, 4, 0, 3), sim=SIM, control=SHORT, box=(6, 6, 6))
    assert torch.equal(fresh.reset(), seen[3])  # the first observation a control env of those bodies gives


def test_a_streams_robot_seconds_count_one_settle_per_cohort_it_builds(monkeypatch) -> None:
    """``population.robot_seconds`` (the budget ``lab.codesign`` charges a population run) against the env
    itself: every control env the stream builds settles its environments once, and every episode runs the window."""
    from types import SimpleNamespace

    from freeform.envs import population

    built = []
    original = ControlEnv.__init__

    def counting(self, grids, *args, **kwargs):
        built.append(len(grids))
        original(self, grids, *args, **kwargs)

    monkeypatch.setattr(ControlEnv, "__init__", counting)
    env = PopulationControlEnv(SIZES, Stream(4, pool=2, refresh_every=2), sim=SIM, control=SHORT, seed=7)
    env.reset()
    run = SimpleNamespace(burn_in=SHORT.burn_in, duration=SHORT.duration, pool=2, refresh_every=2)
    for episodes in range(1, 9):  # (the last step's reset settles the next episode's cohort: counted)
        for _ in range(SHORT.steps):
            env.step(torch.zeros(4, env.action_dim))
        simulated = episodes * 4 * SHORT.duration + sum(built) * SHORT.burn_in
        assert population.robot_seconds(episodes, 4, run, seed=7) == pytest.approx(simulated), episodes
    assert len(built) >= 4  # (eight episodes, a new cohort every two)


def test_a_rank_holds_its_slice_of_every_cohort() -> None:
    whole = PopulationControlEnv(SIZES, Stream(4, pool=3, refresh_every=1), sim=SIM, control=SHORT, seed=2)
    part = PopulationControlEnv(SIZES, Stream(4, pool=3, refresh_every=1), sim=SIM, control=SHORT, seed=2, envs=(2, 4))
    for _ in range(3):
        a, b = whole.reset(), part.reset()
        assert torch.equal(whole.grids[2:], part.grids) and torch.equal(a[2:], b)


def test_bad_streams_are_refused_with_the_reason() -> None:
    with pytest.raises(ValueError, match="pool must be an int >= 1"):
        PopulationControlEnv(SIZES, Stream(4, pool=0))
    with pytest.raises(ValueError, match="refresh_every must be an int >= 0"):
        PopulationControlEnv(SIZES, Stream(4, refresh_every=-1))
    with pytest.raises(ValueError, match="envs must be"):
        PopulationControlEnv(SIZES, Stream(4), envs=(3, 6))


def test_copies_of_a_body_start_alike_and_are_named_as_one_group() -> None:
    steer = ControlConfig(burn_in=0.02, duration=0.025, headings="random", residual=True, ramp=True)
    env = PopulationControlEnv(SIZES, Stream(6, pool=1, copies=3), sim=SIM, control=steer, seed=4)
    obs = env.reset()
    assert env.reward_groups.tolist() == [0, 0, 0, 1, 1, 1]
    assert torch.equal(env.grids[0], env.grids[2]) and not torch.equal(env.grids[0], env.grids[3])
    assert torch.equal(obs[0], obs[1]) and torch.equal(obs[3], obs[5])  # one settled state, one heading per body
    assert torch.equal(env.grids[3], design_cohort(SIZES, 2, 0, 0)[1])  # the cohort's second body
    actions = torch.zeros(6, env.action_dim)
    actions[1] = 0.5  # one copy acts otherwise: only its reward moves
    _, reward, _, _ = env.step(actions)
    assert reward[0] == reward[2] and reward[0] != reward[1] and reward[3] == reward[4] == reward[5]
    part = PopulationControlEnv(SIZES, Stream(6, pool=1, copies=3), sim=SIM, control=steer, seed=4, envs=(3, 6))
    assert torch.equal(part.reset(), obs[3:]) and part.reward_groups.tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="copies = 4 must divide"):
        PopulationControlEnv(SIZES, Stream(6, copies=4))
    with pytest.raises(ValueError, match="copies = 3 must divide the cohort's 6 environments and this process's "
                                         "slice 2..6"):
        PopulationControlEnv(SIZES, Stream(6, copies=3), envs=(2, 6))


def test_the_group_baseline_subtracts_the_siblings_mean_and_needs_groups() -> None:
    from freeform.agents import PPO, PPOConfig
    from freeform.agents.networks.controllers import ConvController
    from freeform.agents.ppo.losses import leave_one_out

    rewards = torch.tensor([[1.0, 3.0, 10.0, 20.0, 30.0], [0.0, 0.0, 1.0, 1.0, 4.0]])
    expected = torch.tensor([[-2.0, 2.0, -15.0, 0.0, 15.0], [0.0, 0.0, -1.5, -1.5, 3.0]])
    torch.testing.assert_close(leave_one_out(rewards, torch.tensor([0, 0, 1, 1, 1])), expected)
    env = ControlEnv(design_cohort(SIZES, 2, 0, 0), sim=SIM, control=SHORT)
    with pytest.raises(ValueError, match="group_baseline needs an env that names each environment's group"):
        PPO(env, ConvController.for_env(env, hidden=4), PPOConfig(group_baseline=True))
    env.reward_groups = torch.tensor([0, 1])
    with pytest.raises(ValueError, match=r"used by >= 2 environments \(copies\), got \[0, 1\]"):
        PPO(env, ConvController.for_env(env, hidden=4), PPOConfig(group_baseline=True))


def tiny_population(*overrides: str) -> list[str]:
    values = {"experiment": "control_population_steering_cpu", "env.num_envs": 4, "env.resolution": 6,
              "env.steps": 6, "control.burn_in": 0.01, "control.duration": 0.05, "control.pool": 2,
              "control.refresh_every": 1, "control.copies": 2, "control.period": 0.0125, "control.stroke_periods": 1,
              "agent.rollout_steps": 4, "agent.hidden": 4, "agent.sgd_minibatch_size": 8, "trainer.progress": "false",
              "trainer.print_every": 0, "trainer.threads": 1, "trainer.render_every": 0, "trainer.checkpoint_every": 1,
              "sim.precision": "f64", "seed": 3}
    for override in overrides:
        key, value = override.split("=", 1)
        values[key] = value
    return [f"{k}={v}" for k, v in values.items()]


def test_a_population_run_resumes_bit_for_bit_on_fresh_bodies(tmp_path: Path) -> None:
    straight, split = straight_and_resumed(compose(*tiny_population()), tmp_path, epochs=3)
    a, b = (load_checkpoint(d / "checkpoints" / "last.pt")["ppo"] for d in (straight, split))
    for name, tensor in a["policy"].items():
        assert torch.equal(tensor, b["policy"][name]), name
    records = [read_record(straight / "records" / f"epoch_{e:06d}.npz") for e in range(3)]
    again = read_record(split / "records" / "epoch_000002.npz")
    np.testing.assert_array_equal(records[2].rewards, again.rewards)
    np.testing.assert_array_equal(records[2].final_grids, again.final_grids)
    assert len({r.final_grids.tobytes() for r in records}) >= 2  # not one body set: the stream moved


def _residual(rate: float | None) -> ControlEnv:
    grids = np.zeros((1, 3, 3, 3), np.uint8)
    grids[0, :, 1, 0] = (2, 1, 3)  # muscle A, passive, muscle B
    control = ControlConfig(burn_in=0.05, duration=0.1, period=0.0125, residual=True, ramp=True, command_rate=rate)
    return ControlEnv(grids, sim=SIM, control=control)


def test_a_bandwidth_above_the_sines_lets_the_open_loop_gait_through_bit_for_bit() -> None:
    free, limited = _residual(None), _residual(26.0)  # 2 pi 4 Hz = 25.1 /s: the sine's own fastest change
    assert torch.equal(free.reset(), limited.reset())
    for _ in range(free.control.steps):
        a, b = free.step(torch.zeros(1, free.action_dim)), limited.step(torch.zeros(1, limited.action_dim))
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_the_bandwidth_limits_the_sine_plus_the_correction() -> None:
    env, rate = _residual(5.0), 5.0
    env.reset()
    period, T = env.control.period, env.sim_config.temp_period
    received, actuated = env._received.copy(), env._actuated.astype(bool)
    for step in range(env.control.steps - 1):  # (the last step's reset starts the next episode's commands)
        env.step(torch.full((1, env.action_dim), 2.0))  # the largest correction asked for, every step
        end = (env.control.burn_in + (step + 1) * period) / T
        sine = np.sin(2 * math.pi * (end + env._phase))
        total = np.clip(sine + env._command, -1.0, 1.0)  # what the kernels give a muscle at the period's end
        change = total[actuated] - received[actuated]
        assert np.all(np.abs(change) <= rate * period + 1e-12)
        np.testing.assert_allclose(change, np.minimum(rate * period, np.clip(sine + 2.0, -1, 1) - received)[actuated])
        received = total


def test_a_designers_stream_is_the_bodies_its_design_env_builds_under_its_policy(tmp_path: Path) -> None:
    """``control.designer=RUN``: the stream's bodies are what RUN's last policy designs — each cohort the largest
    components of the final grids its own ``DesignEnv.step`` builds when ``PPO.act`` draws from a generator seeded
    the cohort's way — and a run of the wrong sizes, a control run or a designer without a population are refused."""
    from freeform import train as train_mod
    from freeform.agents import PPO
    from freeform.body import largest_component
    from freeform.envs.design import DesignEnv, EnvConfig
    from freeform.run.designer import TrainedDesigner, trained_design_bodies

    design = ["experiment=volume_cpu", "env.num_envs=4", "env.resolution=6", "env.steps=6", "env.bundle_size=2",
              "task.materials=4", "agent.hidden=4", "agent.sgd_minibatch_size=8", "trainer.epochs=2",
              "trainer.progress=false", "trainer.print_every=0", "trainer.threads=1", "trainer.render_every=0"]
    train_mod.train(compose(*design), tmp_path / "design")
    run = str(tmp_path / "design")
    bodies = trained_design_bodies(run, 5, SIZES, 7)
    ppo = PPO.load(tmp_path / "design" / "checkpoints" / "last.pt", DesignEnv(4, EnvConfig(resolution=6, steps=6)))
    ppo.generator.manual_seed(7)
    env = DesignEnv(5, EnvConfig(resolution=6, steps=6, bundle_size=2), materials=4)
    obs, done = env.reset(), torch.zeros(5, dtype=torch.bool)
    while not bool(done.all()):
        obs, _, done, info = env.step(ppo.act(obs))
    assert torch.equal(bodies, largest_component(info["final_grids"]))
    assert not torch.equal(bodies, trained_design_bodies(run, 5, SIZES, 8))  # another draw, other designs
    designed = DesignBodies(6, 4, 6, 2, designer=TrainedDesigner(run))
    assert torch.equal(design_cohort(designed, 4, 0, 1), design_cohort(designed, 4, 0, 1))
    assert not torch.equal(design_cohort(designed, 4, 0, 1), design_cohort(SIZES, 4, 0, 1))  # not untrained ones
    stream = PopulationControlEnv(designed, Stream(4, pool=1, refresh_every=1), sim=SIM, control=SHORT, seed=1)
    stream.reset()
    assert torch.equal(stream.grids, design_cohort(designed, 4, 0, stream.cohort_at(0)))
    with pytest.raises(ValueError, match=r"designs on a 6\^3 grid .* this run's design sizes"):
        trained_design_bodies(run, 2, DesignBodies(8, 4, 6, 2), 0)
    with pytest.raises(ValueError, match="control.designer=.*no such checkpoint"):
        trained_design_bodies(str(tmp_path / "nothing"), 2, SIZES, 0)
    with pytest.raises(ValueError, match="control.designer.*with bodies=population"):
        compose("experiment=control_locomotion_cpu", f"control.designer={run}")
    train_mod.train(compose(*tiny_population("trainer.epochs=1")), tmp_path / "control")
    with pytest.raises(ValueError, match="a control run's checkpoint; the designer is a design run"):
        trained_design_bodies(str(tmp_path / "control"), 2, SIZES, 0)
