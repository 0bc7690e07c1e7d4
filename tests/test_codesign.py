"""Design then control in one episode (freeform/envs/codesign.py, CodesignActorCritic): the design stage builds what
the design env builds from the same actions, the control stage scores what a control env of those bodies scores
under the same commands, an empty body is frozen at reward 0, the policy's mask follows the stage, and PPO trains
the whole thing."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from freeform.agents import PPO, CodesignActorCritic, PPOConfig
from freeform.agents.networks import rebuild
from freeform.agents.networks.controller_heads import ControlInputs
from freeform.body import largest_component
from freeform.config import EnvConfig
from freeform.envs import CodesignEnv, DesignEnv
from freeform.envs.codesign import CODESIGN_CHANNELS, CONTROL, GRID, STAGE
from freeform.envs.control import OBS_CHANNELS, ControlConfig, ControlEnv
from freeform.sim import SimConfig

RHO, K, T = 6, 4, 4
CONTROL_CFG = ControlConfig(burn_in=0.01, duration=0.0375, headings="random")  # 3 control steps


def env(n: int = 3, seed: int = 2, control: ControlConfig = CONTROL_CFG) -> CodesignEnv:
    return CodesignEnv(n, EnvConfig(resolution=RHO, steps=T), K, SimConfig(precision="f64"), control, seed=seed)


def design_actions(n: int, gen: torch.Generator) -> list[torch.Tensor]:
    """T design actions that place a material 1 … k−1 (never erase) at random positions near the centre."""
    actions = [torch.randn(n, 3 + K, generator=gen) * 0.7 for _ in range(T)]
    for a in actions:
        a[:, 3:] = torch.eye(K)[torch.randint(1, K, (n,), generator=gen)] * 5
    return actions


@pytest.mark.parametrize("residual", [False, True])
def test_an_episode_designs_as_the_design_env_and_controls_as_the_control_env(residual: bool) -> None:
    gen = torch.Generator().manual_seed(0)
    control = replace(CONTROL_CFG, residual=residual)
    e = env(control=control)
    n, width = e.num_envs, e.action_dim
    obs = e.reset()
    channels = len(CODESIGN_CHANNELS) + residual  # residual control: the open-loop sine's channel last
    assert tuple(obs.shape) == (n, channels, RHO, RHO, RHO) and width == 3 + K + RHO ** 3
    assert e.control_channels == (CONTROL.start, channels)
    design = DesignEnv(n, EnvConfig(resolution=RHO, steps=T), materials=K, compute_metrics=False)
    design.reset()
    acts = design_actions(n, gen)
    for a in acts:
        assert e.stage == "design" and float(obs[:, STAGE].abs().max()) == 0.0
        full = torch.cat([a, torch.rand(n, RHO ** 3, generator=gen)], 1)  # the commands' part is ignored here
        obs, reward, done, info = e.step(full)
        design.grids = design.place_bundles(design.grids, a)
        assert not done.any() and float(reward.abs().max()) == 0.0 and info == {}
        assert torch.equal(obs[:, GRID].to(torch.uint8), design.grids)
    assert e.stage == "control" and bool((obs[:, STAGE] == 1).all())
    bodies = largest_component(design.grids)
    alive = (bodies.flatten(1) > 0).any(dim=1)
    # the reference: a control env of the same bodies, its headings drawn as the co-design env's
    ref = ControlEnv(bodies[alive], sim=SimConfig(precision="f64"), control=control, seed=2,
                     first_env=torch.nonzero(alive).flatten().numpy())
    ref_obs = ref.reset(episode=0)
    np.testing.assert_array_equal(e.heading[alive.numpy()], ref.heading)
    torch.testing.assert_close(obs[alive][:, CONTROL.start:], ref.to_grid(ref_obs), rtol=0, atol=0)
    total = torch.zeros(n)
    for step in range(CONTROL_CFG.steps):
        commands = torch.rand(n, RHO ** 3, generator=gen) * 2 - 1
        obs, reward, done, info = e.step(torch.cat([torch.zeros(n, 3 + K), commands], 1))
        ref_obs, ref_reward, _, _ = ref.step(ref.from_grid(commands[alive].view(-1, RHO, RHO, RHO)))
        torch.testing.assert_close(reward[alive], ref_reward, rtol=0, atol=0)
        total += reward
        assert bool(done.all()) == (step == CONTROL_CFG.steps - 1)
    assert float(reward[~alive].abs().sum()) == 0.0 and bool(info["failed"].eq(~alive).all())
    assert torch.equal(info["final_grids"], design.grids) and torch.equal(info["bodies"], bodies)
    assert info["metrics"]["volume"].tolist() == (bodies > 0).flatten(1).sum(1).float().tolist()
    assert bool(info["truncated"].all()) and e.stage == "design" and float(obs[:, GRID].abs().max()) == 0.0
    assert float(total[alive].abs().min()) > 0  # the bodies moved


def test_an_empty_body_is_frozen_with_reward_zero() -> None:
    e = env(n=2)
    e.reset()
    erase = torch.zeros(2, e.action_dim)
    erase[:, 3] = 5.0  # material 0 everywhere it paints: nothing is ever built
    for _ in range(T):
        obs, *_ = e.step(erase)
    assert e.controlled is None and float(obs[:, CONTROL].abs().max()) == 0.0
    for _ in range(CONTROL_CFG.steps):
        obs, reward, done, info = e.step(torch.ones(2, e.action_dim))
        assert float(reward.abs().max()) == 0.0
    assert bool(info["failed"].all()) and bool(done.all())


def test_the_policy_acts_with_the_design_head_then_the_controller() -> None:
    e = env(n=2)
    policy = CodesignActorCritic.for_env(e, hidden=8, controller_hidden=4)
    obs = e.reset()
    mean, log_std, mask, value = policy(obs)
    assert mask.shape == (2, e.action_dim)
    assert bool((mask[:, : 3 + K] == 1).all()) and float(mask[:, 3 + K:].abs().max()) == 0.0
    build = torch.zeros(2, e.action_dim)
    build[:, 3 + 2] = 5.0  # muscle A at the centre, every step
    for _ in range(T):
        obs, *_ = e.step(build)
    mean, log_std, mask, value = policy(obs)
    actuated = obs[:, CONTROL.start + OBS_CHANNELS.index("actuated")].reshape(2, -1)
    assert float(mask[:, : 3 + K].abs().max()) == 0.0 and torch.equal(mask[:, 3 + K:], actuated)
    assert int(actuated.sum()) == 2 * 8  # one 2³ bundle of muscle each
    design_value = policy.design(obs[:, GRID].to(torch.uint8))[-1]
    assert not torch.allclose(value, design_value)  # the controller's critic counts now


def test_a_stroke_episode_controls_as_the_control_env_with_the_same_strokes() -> None:
    """``control.stroke_periods``: a co-design control action is a stroke's a for every grid cell, then its b; the
    control env given the same strokes on its box (moved onto the grids by ``to_grid``, its inverse) moves the
    bodies the same, bit for bit."""
    gen = torch.Generator().manual_seed(1)
    control = replace(CONTROL_CFG, stroke_periods=1, residual=True)
    e = env(control=control)
    n = e.num_envs
    assert e.action_channels == 2 and e.action_dim == 3 + K + 2 * RHO ** 3
    e.reset()
    for a in design_actions(n, gen):
        obs, *_ = e.step(torch.cat([a, torch.zeros(n, 2 * RHO ** 3)], 1))
    alive = e._alive
    ref = ControlEnv(e.controlled.grids, sim=SimConfig(precision="f64"), control=control, seed=2,
                     first_env=torch.nonzero(alive).flatten().numpy())
    ref.reset(episode=0)
    for _ in range(control.steps):
        strokes = torch.rand(int(alive.sum()), 2, ref.cells, generator=gen) * 2 - 1
        on_grid = torch.zeros(n, 2 * RHO ** 3)
        on_grid[alive] = ref.to_grid(strokes.view(-1, 2, *ref.box)).reshape(-1, 2 * RHO ** 3)
        _, reward, _, _ = e.step(torch.cat([torch.zeros(n, 3 + K), on_grid], 1))
        _, ref_reward, _, _ = ref.step(strokes.reshape(-1, 2 * ref.cells))
        torch.testing.assert_close(reward[alive], ref_reward, rtol=0, atol=0)
    assert float(ref_reward.abs().min()) > 0


def test_a_codesign_policy_can_hold_a_population_controller() -> None:
    """``CodesignActorCritic.for_env(controller="context", head="wave")`` on a stroke episode: while controlling,
    its action parameters are those of the same controller on the control channels (two numbers a cell, masked to
    the actuated cells); its ``init_kwargs`` rebuild it."""
    from freeform.agents.networks.controllers import ContextConvController

    control = replace(CONTROL_CFG, stroke_periods=1, residual=True, headings="any")
    e = env(n=2, control=control)
    policy = CodesignActorCritic.for_env(e, hidden=8, controller_hidden=4, controller="context", head="wave")
    assert isinstance(policy.controller, ContextConvController) and policy.controller.head == "wave"
    again = rebuild(CodesignActorCritic, policy.init_kwargs)
    again.load_state_dict(policy.state_dict())
    e.reset()
    build = torch.zeros(2, e.action_dim)
    build[:, 3 + 2] = 5.0  # muscle A at the centre, every step
    for _ in range(T):
        obs, *_ = e.step(build)
    mean, log_std, mask, value = policy(obs)
    assert mean.shape == mask.shape == (2, 3 + K + 2 * RHO ** 3)
    c_mean, c_log_std, c_mask, c_value = policy.controller(obs[:, slice(*e.control_channels)])
    torch.testing.assert_close(mean[:, 3 + K:], c_mean, rtol=0, atol=0)
    torch.testing.assert_close(value, c_value, rtol=0, atol=0)
    actuated = obs[:, e.control_channels[0] + OBS_CHANNELS.index("actuated")].reshape(2, -1)
    assert torch.equal(mask[:, 3 + K:], actuated.repeat(1, 2)) and float(mask[:, : 3 + K].abs().max()) == 0.0
    torch.testing.assert_close(again(obs)[0], mean, rtol=0, atol=0)


def test_ppo_trains_body_and_brain_and_saves_between_episodes() -> None:
    torch.manual_seed(0)  # (the weights are the process's draws: a file run before this one must not change them)
    e = env(n=4)
    policy = CodesignActorCritic.for_env(e, hidden=8, controller_hidden=4)
    ppo = PPO(e, policy, PPOConfig(rollout_steps=e.steps, sgd_minibatch_size=8, num_sgd_iter=2, seed=0))
    heads = {"design": policy.design.actor_out.weight, "controller": policy.controller.actor.weight}
    before = {name: w.detach().clone() for name, w in heads.items()}
    stats = ppo.train_epoch()
    assert np.isfinite(stats["episode_reward_mean"])
    for name, w in heads.items():  # both stages' losses reach their own head
        assert not torch.equal(before[name], w), name
    episodes = ppo.episodes()
    assert episodes["final_grids"].shape == (4, RHO, RHO, RHO) and episodes["values"].shape == (4, e.steps)
    state = e.state_dict()
    assert state["episode"] == 1
    e.step(torch.zeros(4, e.action_dim))
    with pytest.raises(ValueError, match="between episodes"):
        e.state_dict()
    other = env(n=4)
    other.load_state_dict(state)
    assert other.episode == 1 and other.t == 0


def tiny_codesign(*overrides: str):
    """``experiment=codesign_steering_cpu`` at this file's sizes: a run of a few seconds."""
    from freeform.config import compose

    return compose("experiment=codesign_steering_cpu", "env.num_envs=4", f"env.resolution={RHO}", f"env.steps={T}",
                   "control.duration=0.0375", "control.burn_in=0.01", "trainer.render_every=0",
                   "agent.sgd_minibatch_size=8", "agent.hidden=8", "control.hidden=4", "trainer.progress=false",
                   "trainer.print_every=0", "trainer.threads=1", *overrides)


def test_a_codesign_run_of_the_app_resumes_bit_for_bit(tmp_path) -> None:
    """``freeform-train experiment=codesign_steering_cpu`` at a tiny size: 2 epochs = 1 + resume 1 (weights, records),
    the records hold the designs and one value per design and control step, and the renders are logged."""
    from helpers import straight_and_resumed
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from freeform.checkpoint import load_checkpoint
    from freeform.records import read_record

    straight_and_resumed(tiny_codesign("trainer.render_every=2", "sim.precision=f64", "seed=4"), tmp_path, epochs=2)
    a, b = (load_checkpoint(tmp_path / d / "checkpoints" / "last.pt")["ppo"] for d in ("straight", "split"))
    for name, tensor in a["policy"].items():
        assert torch.equal(tensor, b["policy"][name]), name
    ra, rb = (read_record(tmp_path / d / "records" / "epoch_000001.npz") for d in ("straight", "split"))
    np.testing.assert_array_equal(ra.rewards, rb.rewards)
    np.testing.assert_array_equal(ra.final_grids, rb.final_grids)
    assert ra.values.shape == (4, T + 3) and ra.final_grids.shape == (4, RHO, RHO, RHO)
    events = EventAccumulator(str(tmp_path / "straight"), size_guidance={"images": 0})
    events.Reload()
    assert "bodies/best" in events.Tags()["images"]  # (the gait GIF only when the policy's mode builds a body)


def test_a_recorded_episode_designs_then_drives_the_body() -> None:
    e = env(n=2)
    build = torch.zeros(2, e.action_dim)
    build[:, 3 + 2] = 5.0  # muscle A at the centre, every design step
    build[:, 3 + K:] = 1.0  # then every command at its top
    recording, commands, total = e.record(lambda obs: build)
    # (a frame at the window's start, then one after each decision, the last included)
    assert len(recording.times) == CONTROL_CFG.steps + 1 and recording.positions[0].shape == (CONTROL_CFG.steps + 1, 8, 3)
    assert commands.shape == (CONTROL_CFG.steps, 8) and bool((commands == 1).all()) and total != 0
    assert e.t == 0 and e.stage == "design"
    erase = torch.zeros(2, e.action_dim)
    erase[:, 3] = 5.0
    assert e.record(lambda obs: erase) is None


def test_a_codesign_run_takes_the_agents_trunk() -> None:
    """``agent.trunk`` reaches a co-design policy's design network (as the design env's), and its ``init_kwargs``
    rebuild it; "auto" leaves them as files from before the key hold them."""
    import torch

    from freeform.config import compose
    from freeform.run.build import build

    cfg = compose("experiment=codesign_locomotion_cpu", "env.num_envs=4", "agent.trunk=gather")
    _, ppo = build(cfg, torch.device("cpu"))
    assert ppo.policy.design.trunk == "gather" and ppo.policy.init_kwargs["trunk"] == "gather"
    assert rebuild(CodesignActorCritic, ppo.policy.init_kwargs).design.trunk == "gather"
    assert "trunk" not in CodesignActorCritic.for_env(env(n=2), hidden=8, controller_hidden=4).init_kwargs


def test_a_codesign_run_refuses_the_mlp_controller() -> None:
    from freeform.config import compose

    with pytest.raises(ValueError, match=r"control\.controller must be one of \['conv', 'context', 'attention', 'attention_hyper'\] "
                                         r"with bodies=codesign"):
        compose("experiment=codesign_locomotion_cpu", "control.controller=mlp")
    with pytest.raises(ValueError, match=r"control\.controller must be one of .* with bodies=codesign"):
        compose("experiment=codesign_locomotion_cpu", "control.controller=context_gru")


def test_the_evaluation_of_a_codesign_run_writes_its_tables(tmp_path) -> None:
    """``python -m lab.control --evaluate RUN``: the untrained and trained policy on the same fresh headings,
    each against its own designs' open-loop gaits, with the designs' metrics."""
    import csv

    from freeform import train as train_mod
    from lab.control import main

    train_mod.train(tiny_codesign("trainer.epochs=1"), tmp_path / "run")
    main(["--evaluate", str(tmp_path / "run"), "--eval-episodes", "8", "--out", str(tmp_path / "eval")])
    rows = list(csv.DictReader(open(tmp_path / "eval" / "summary.csv")))
    assert [r["what"].split(" (")[0] for r in rows] == [
        "open loop: the untrained policy's designs along the same headings", "design + controller, untrained",
        "open loop: the trained policy's designs along the same headings", "design + controller, trained"]
    assert all(int(r["n"]) == 8 for r in rows)
    metrics = list(csv.DictReader(open(tmp_path / "eval" / "metrics.csv")))
    assert [m["policy"] for m in metrics] == ["untrained", "trained"] and "symmetry" in metrics[0]
    assert (tmp_path / "eval" / "codesign_steering_cpu.png").is_file()
    # the trained controller part, self-contained beside the tables (--evaluate DIR --bodies reads it)
    from freeform.agents.controller_file import read_controller
    from freeform.checkpoint import load_checkpoint

    saved = read_controller(tmp_path / "eval")
    weights = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["ppo"]["policy"]
    assert saved.kind == "conv" and saved.controller.box == (RHO,) * 3 and saved.control.headings == "random"
    assert all(torch.equal(v, weights[f"controller.{k}"]) for k, v in saved.controller.state_dict().items())


def test_the_comparison_with_the_baselines_counts_robot_seconds_and_writes_its_tables(tmp_path) -> None:
    """``python -m lab.codesign``: a co-design run, an open-loop design run in the co-design episode's window
    and a design-then-control run on the design run's first epoch, scored on 8 episodes each; the robot-seconds
    are the hand count of each run's simulated windows."""
    import csv

    from freeform import train as train_mod
    from freeform.config import compose
    from lab.codesign import _last, main

    burn_in, duration = 0.01, 0.0375
    common = ["env.num_envs=4", f"env.resolution={RHO}", f"env.steps={T}", "trainer.render_every=0",
              "agent.sgd_minibatch_size=8", "trainer.progress=false", "trainer.print_every=0", "trainer.threads=1"]
    window = [f"control.burn_in={burn_in}", f"control.duration={duration}"]
    train_mod.train(compose("experiment=codesign_locomotion_cpu", "trainer.epochs=1", "agent.hidden=8",
                            "control.hidden=4", f"agent.rollout_steps={2 * (T + 3)}", *window, *common),
                    tmp_path / "codesign")  # (two episodes an epoch: T design steps and 3 control decisions each)
    train_mod.train(compose("experiment=locomotion_cpu", "trainer.epochs=2", "agent.hidden=8", "+task.options.measure=com",
                            f"sim.burn_in={burn_in}", f"sim.duration={duration}", *common), tmp_path / "open_loop")
    record = tmp_path / "open_loop" / "records" / "epoch_000000.npz"
    train_mod.train(compose("experiment=control_locomotion_cpu", f"control.bodies={record}", "control.top=2",
                            "trainer.epochs=1", "agent.hidden=4", "agent.rollout_steps=6", *window, *common),
                    tmp_path / "two_stage")  # (a rollout of two episodes of 3 decisions an environment)
    main(["--codesign", str(tmp_path / "codesign"), "--open-loop", str(tmp_path / "open_loop"),
          "--two-stage", str(tmp_path / "two_stage"), "--episodes", "8", "--out", str(tmp_path / "out")])
    rows = list(csv.DictReader(open(tmp_path / "out" / "summary.csv")))
    seconds = {r["method"].strip(): float(r["robot_seconds"]) for r in rows}
    assert [r["method"].strip() for r in rows] == [
        "co-design (one PPO: body, then controller)", "its designs, open loop", "open-loop design RL (the paper's)",
        "design, then control (2 best designs)", "its bodies, open loop"]
    assert all(int(r["n"]) == 8 for r in rows)
    assert [r["score"] for r in rows] == ["move along +x, controlled", "move in the plane, sine gait",
                                          "move in the plane, sine gait", "move along +x, controlled",
                                          "move in the plane, sine gait"]  # (each what it was trained for)
    window_s = burn_in + duration
    assert seconds["co-design (one PPO: body, then controller)"] == pytest.approx(1 * 4 * 2 * window_s, abs=1e-3)
    assert seconds["open-loop design RL (the paper's)"] == pytest.approx(2 * 4 * window_s, abs=1e-3)
    assert seconds["design, then control (2 best designs)"] == pytest.approx(
        1 * 4 * window_s + 1 * 4 * 2 * duration + 4 * burn_in, abs=1e-3)  # (each of the 4 envs' copies settles once)
    # the same from the steps the run took, a control period each
    two_stage, last = _last(tmp_path / "two_stage")
    played = last["ppo"]["global_step"] * two_stage.control.period
    assert seconds["design, then control (2 best designs)"] == pytest.approx(1 * 4 * window_s + played + 4 * burn_in)
    assert all(float(r["mean"]) >= 0 for r in rows if "open loop" in r["score"] or "sine" in r["score"])
    metrics = list(csv.DictReader(open(tmp_path / "out" / "metrics.csv")))
    assert len(metrics) == len(rows) and float(metrics[2]["volume"]) > 0
    for m in metrics:  # each method's designs' diversity (freeform.body.diversity, tested against scipy)
        assert 0.0 <= float(m["distance"]) <= 1.0 and 1 <= int(m["distinct"]) <= 8
    (tmp_path / "out" / "codesign_vs_baselines.png").unlink()
    main(["--replot", "--out", str(tmp_path / "out")])  # the figure again, from the tables alone
    assert (tmp_path / "out" / "codesign_vs_baselines.png").is_file()


def test_a_codesign_run_can_start_from_a_trained_controller(tmp_path) -> None:
    """``control.controller_init=RUN``: the co-design run's epoch-0 controller is RUN's trained controller, weight for
    weight (its design network is fresh), and so is one started from its ``controller.pt``; a controller of another
    width is refused naming the key."""
    from freeform import train as train_mod
    from freeform.agents.controller_file import read_controller, save_controller
    from freeform.checkpoint import load_checkpoint
    from freeform.config import compose
    from freeform.run.build import load_controller

    size = ["env.num_envs=4", f"env.resolution={RHO}", f"env.steps={T}", "control.duration=0.0375",
            "control.burn_in=0.01", "trainer.render_every=0", "agent.sgd_minibatch_size=8", "control.hidden=4",
            "trainer.progress=false", "trainer.print_every=0", "trainer.threads=1", "trainer.epochs=1"]
    train_mod.train(compose("experiment=control_steering_cpu", "control.bodies=untrained_designs", *size),
                    tmp_path / "control")
    trained = load_checkpoint(tmp_path / "control" / "checkpoints" / "last.pt")["ppo"]["policy"]
    train_mod.train(compose("experiment=codesign_steering_cpu", "agent.hidden=8", *size,
                            f"control.controller_init={tmp_path / 'control'}"), tmp_path / "codesign")
    start = load_checkpoint(tmp_path / "codesign" / "checkpoints" / "epoch_000000.pt")["ppo"]["policy"]
    assert set(trained) == {k[len("controller."):] for k in start if k.startswith("controller.")}
    for name, tensor in trained.items():
        assert torch.equal(start[f"controller.{name}"], tensor), name
    saved = read_controller(tmp_path / "control")  # the self-contained file of it starts a controller the same way
    save_controller(tmp_path / "controller.pt", saved.controller, saved.control, saved.sim)
    fresh = rebuild(type(saved.controller), saved.controller.init_kwargs)
    load_controller(fresh, str(tmp_path / "controller.pt"))
    for name, tensor in fresh.state_dict().items():
        assert torch.equal(tensor, trained[name]), name
    with pytest.raises(ValueError, match="control.controller_init=.*another controller"):
        train_mod.train(compose("experiment=codesign_steering_cpu", "agent.hidden=8", *size, "control.hidden=6",
                                f"control.controller_init={tmp_path / 'control'}"), tmp_path / "wide")
    with pytest.raises(ValueError, match="control.controller_init=.*no such checkpoint"):
        train_mod.train(compose("experiment=codesign_steering_cpu", *size,
                                f"control.controller_init={tmp_path / 'nothing'}"), tmp_path / "none")


@pytest.mark.slow
def test_design_after_control_is_charged_its_controllers_pretraining(tmp_path) -> None:
    """``python -m lab.codesign --designed RUN --pretraining ...``: a design run whose designs a frozen
    controller drives (``task.name=controlled_locomotion``) beside open-loop design RL; its budget is its epochs of
    controlled episodes (the controller's settling and window) plus the control run's that the overrides describe —
    here a fixed population (one cohort, settled once), so the hand count is exact."""
    import csv

    from freeform import train as train_mod
    from freeform.agents.controller_file import save_controller
    from freeform.agents.networks.controllers import ContextConvController
    from freeform.config import compose
    from freeform.envs.control import RESIDUAL_CHANNELS
    from lab.codesign import main

    episode = ControlConfig(burn_in=0.01, duration=0.0375, headings="any", residual=True)
    net = ContextConvController(ControlInputs(len(RESIDUAL_CHANNELS), (RHO,) * 3, RESIDUAL_CHANNELS.index("actuated")),
                                hidden=4)
    save_controller(tmp_path / "controller.pt", net, episode, SimConfig())
    common = ["env.num_envs=4", f"env.resolution={RHO}", f"env.steps={T}", "trainer.render_every=0", "agent.hidden=8",
              "agent.sgd_minibatch_size=8", "trainer.progress=false", "trainer.print_every=0", "trainer.threads=1"]
    train_mod.train(compose("experiment=controlled_design_cpu", "trainer.epochs=2",
                            f"task.options.controller={tmp_path / 'controller.pt'}", *common), tmp_path / "designed")
    tiny_open_loop(tmp_path / "open_loop", *common)
    pretraining, before = fixed_population(epochs=3)
    main(["--designed", str(tmp_path / "designed"), "--open-loop", str(tmp_path / "open_loop"), "--episodes", "4",
          "--out", str(tmp_path / "out"), "--pretraining", *pretraining])
    rows = {r["method"].strip(): r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    designed = rows[f"design after control (frozen: {tmp_path.name})"]  # (controller.pt's folder names it)
    assert float(designed["pretraining_robot_seconds"]) == pytest.approx(before, abs=1e-3)
    assert float(designed["robot_seconds"]) == pytest.approx(before + 2 * 4 * (0.01 + 0.0375), abs=1e-3)
    assert designed["score"] == "move in the plane, controlled" and int(designed["n"]) == 4
    assert rows["its designs, open loop"]["score"] == "move in the plane, sine gait"
    assert float(rows["open-loop design RL (the paper's)"]["robot_seconds"]) == pytest.approx(4 * 0.0475, abs=1e-3)
    driven = rows["open-loop design RL's designs, driven by the same controller"]  # (no training beyond both runs)
    assert float(driven["robot_seconds"]) == pytest.approx(before + 4 * 0.0475, abs=1e-3)
    assert driven["score"] == "move in the plane, controlled" and int(driven["n"]) == 4
    # a controller adapted to the designs (control.designer): it drives the same designs, its own epochs added
    adapted = ["experiment=control_population_cpu", "trainer.epochs=1", *common, "control.hidden=4",
               "control.head=direct", "control.stroke_periods=0", "control.period=0.0125", "control.burn_in=0.01",
               "control.duration=0.0375", "agent.rollout_steps=3", "control.copies=2", "control.pool=1",
               "control.refresh_every=0", f"control.designer={tmp_path / 'designed'}",
               f"control.controller_init={tmp_path / 'controller.pt'}"]
    train_mod.train(compose(*adapted), tmp_path / "adapted")
    train_mod.train(compose(*adapted[:-2], f"control.controller_init={tmp_path / 'controller.pt'}"),
                    tmp_path / "more")  # (its control: as long again on untrained bodies)
    main(["--designed", str(tmp_path / "designed"), "--open-loop", str(tmp_path / "open_loop"), "--episodes", "4",
          "--out", str(tmp_path / "out2"), "--pretraining", *pretraining, "--adapted", str(tmp_path / "adapted"),
          str(tmp_path / "more")])
    rows = {r["method"].strip(): r for r in csv.DictReader(open(tmp_path / "out2" / "summary.csv"))}
    row = rows["its designs, the controller adapted to them (1 epochs on their stream)"]
    adapting = 4 * 0.0375 + 4 * 0.01  # (one episode, one cohort settled)
    assert float(row["robot_seconds"]) == pytest.approx(before + 2 * 4 * 0.0475 + adapting, abs=1e-3)
    assert row["score"] == "move in the plane, controlled" and int(row["n"]) == 4
    assert row["mean"] != designed["mean"]  # (another controller: its trained weights moved)
    more = "the controller trained 1 more epochs on untrained bodies"
    assert float(rows[f"its designs, {more}"]["robot_seconds"]) == pytest.approx(float(row["robot_seconds"]))
    assert float(rows[f"open-loop design RL's designs, {more}"]["robot_seconds"]) == pytest.approx(
        before + 4 * 0.0475 + adapting, abs=1e-3)
    assert "open-loop design RL's designs, the controller adapted to them (1 epochs on their stream)" not in rows


def test_a_codesign_run_starts_from_a_population_controllers_file(tmp_path) -> None:
    """A co-design run with a population controller's kind, head and strokes (``control.controller=context
    control.head=wave control.stroke_periods=1``) started from its ``controller.pt``: the epoch-0 controller is the
    file's, weight for weight, and the run's controller reads back (``read_controller``) as that kind."""
    from freeform import train as train_mod
    from freeform.agents.controller_file import read_controller, save_controller
    from freeform.agents.networks.controllers import build_controller
    from freeform.checkpoint import load_checkpoint
    from freeform.config import compose
    from freeform.run.build import control_env

    overrides = ["experiment=codesign_locomotion_cpu", "env.num_envs=4", f"env.resolution={RHO}", f"env.steps={T}",
                 "control.duration=0.0375", "control.burn_in=0.01", "control.controller=context", "control.head=wave",
                 "control.stroke_periods=1", "control.residual=true", "control.headings=any", "control.hidden=4",
                 "agent.hidden=8", f"agent.rollout_steps={T + 3}", "agent.sgd_minibatch_size=8",
                 "trainer.render_every=0", "trainer.progress=false", "trainer.print_every=0", "trainer.threads=1",
                 "trainer.epochs=1"]
    cfg = compose(*overrides)
    env = control_env(cfg, torch.device("cpu"), (0, 4), 0)
    net = build_controller("context", env.control_view(), 4, -0.5, "wave")
    with torch.no_grad():
        for param in net.parameters():
            param.add_(torch.randn_like(param) * 0.1)  # (not what a fresh controller starts from)
    save_controller(tmp_path / "controller.pt", net, cfg.control, cfg.sim)
    train_mod.train(compose(*overrides, f"control.controller_init={tmp_path / 'controller.pt'}"), tmp_path / "run")
    start = load_checkpoint(tmp_path / "run" / "checkpoints" / "epoch_000000.pt")["ppo"]["policy"]
    for name, tensor in net.state_dict().items():
        assert torch.equal(start[f"controller.{name}"], tensor), name
    saved = read_controller(tmp_path / "run")
    assert saved.kind == "context" and saved.controller.head == "wave"
    for other, theirs in (("control.wave_amplitude=1.6", "amplitude 1.6, gain 1.0"),
                          ("control.wave_gain=2.0", "amplitude 1.0, gain 2.0")):
        with pytest.raises(ValueError, match=rf"hand-set wave k = 1.0, amplitude 1.0 at gain 1.0; this run's is k = "
                                             rf"1.0, {theirs}: set control.wave_k, control.wave_amplitude and "
                                             r"control.wave_gain"):
            train_mod.train(compose(*overrides, f"control.controller_init={tmp_path / 'controller.pt'}", other),
                            tmp_path / "other_wave")
    # the comparison charges the warm start's training to co-design's budget (--pretraining)
    import csv

    from lab.codesign import main

    tiny_open_loop(tmp_path / "open_loop", "env.num_envs=4", f"env.resolution={RHO}", f"env.steps={T}",
                   "agent.hidden=8", "trainer.render_every=0", "trainer.progress=false", "trainer.print_every=0",
                   "trainer.threads=1")
    pretraining, before = fixed_population(epochs=1)
    main(["--codesign", str(tmp_path / "run"), "--open-loop", str(tmp_path / "open_loop"), "--episodes", "4",
          "--out", str(tmp_path / "out"), "--pretraining", *pretraining])
    rows = {r["method"].strip(): r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    row = rows[f"co-design from {tmp_path.name} (one PPO: body, then controller)"]  # (its warm start's folder)
    assert float(row["pretraining_robot_seconds"]) == pytest.approx(before, abs=1e-3)
    assert float(row["robot_seconds"]) == pytest.approx(before + 4 * (0.01 + 0.0375), abs=1e-3)
    # ... and what its joint update added: its designs, and the paper's at their budget plus the warm start's,
    # driven by the warm start, frozen
    assert int(rows["its designs, driven by the warm-start controller (frozen)"]["n"]) == 4
    paper = float(rows["open-loop design RL (the paper's)"]["robot_seconds"])
    driven = rows["open-loop design RL's designs, driven by the warm-start controller (frozen)"]
    assert float(driven["robot_seconds"]) == pytest.approx(before + paper, abs=1e-3)
    # a student's lineage is charged as run directories (--pretraining-runs), each for the epochs it ran: here the
    # open-loop run and the co-design run, one epoch of 4 bodies' windows each
    from lab.codesign import pretraining_seconds

    seconds, what = pretraining_seconds(pretraining, [tmp_path / "open_loop", tmp_path / "run"])
    assert seconds == pytest.approx(before + 2 * 4 * (0.01 + 0.0375), abs=1e-3)
    assert f"{tmp_path / 'run'} (1 epochs)" in what
    with pytest.raises(SystemExit, match="no checkpoints/last.pt"):
        pretraining_seconds(None, [tmp_path])
    # a pooled teacher folder stands for the runs it pooled, each at the epoch its teachers were taken (here 2, where
    # the run itself stopped at 1); a run named beside the pool that holds it would be charged twice
    pooled = tmp_path / "pooled"
    pooled.mkdir()
    (pooled / "pooled.json").write_text(json.dumps({"teachers": 4, "sources": [
        {"run": str(tmp_path / "run"), "teachers": [0, 4], "epoch": 2}]}))
    one_epoch = pretraining_seconds(None, [tmp_path / "run"])[0]
    seconds, what = pretraining_seconds(None, [pooled])
    assert seconds == pytest.approx(2 * one_epoch) and f"(2 epochs, pooled in {pooled})" in what
    with pytest.raises(SystemExit, match="charged twice"):
        pretraining_seconds(None, [pooled, tmp_path / "run"])
    # a copy of a run (trained on from where it was copied) shares its rollouts up to there: one origin is charged
    # once, for the most epochs any copy reached — the pool's 2 epochs of the run, then its copy's 1, in either order
    import shutil

    shutil.copytree(tmp_path / "run", tmp_path / "run_copy")
    assert pretraining_seconds(None, [tmp_path / "run", tmp_path / "run_copy"])[0] == pytest.approx(one_epoch)
    for order in ([pooled, tmp_path / "run_copy"], [tmp_path / "run_copy", pooled]):
        seconds, what = pretraining_seconds(None, order)
        assert seconds == pytest.approx(2 * one_epoch) and what.count("charged there") == 1
        assert f"{tmp_path / 'run_copy'} (1 epochs): the same run as {tmp_path / 'run'} (copied), charged there" in what
    from lab.codesign import warm_start_name

    assert warm_start_name("lab/results/control_population/controller.pt") == "the population controller"
    assert warm_start_name("population") == "the population controller"  # (the presets name the zoo's)
    assert warm_start_name("runs/student/checkpoints/last.pt") == warm_start_name("runs/student") == "student"


def tiny_open_loop(run, *overrides: str) -> None:
    """A one-epoch open-loop design run in the tiny control window (0.01 s settling, 0.0375 s), the baseline of the
    comparisons above."""
    from freeform import train as train_mod
    from freeform.config import compose

    train_mod.train(compose("experiment=locomotion_cpu", "trainer.epochs=1", "+task.options.measure=com",
                            "sim.burn_in=0.01", "sim.duration=0.0375", *overrides), run)


def fixed_population(epochs: int) -> tuple[list[str], float]:
    """The overrides of a population run of one fixed cohort of 8 bodies (settled once) for ``epochs`` epochs, and
    its robot-seconds counted by hand: every episode's window, one settle."""
    from freeform.config import compose

    overrides = ["experiment=control_population_cpu", f"trainer.epochs={epochs}", "env.num_envs=8", "control.pool=1",
                 "control.refresh_every=0"]
    population = compose(*overrides)
    episodes = epochs * population.agent.rollout_steps // population.control.steps
    return overrides, episodes * 8 * population.control.duration + 8 * population.control.burn_in
