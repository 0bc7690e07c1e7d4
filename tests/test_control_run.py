"""A control run in the training app (``control`` section, ``experiment=control_*``): the command line end to end,
exact resume, the bodies' sources, and the refusals. The control env's physics and the controllers are tested in
test_control_env.py and test_controllers.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import run_cli, scalars, straight_and_resumed

from freeform.checkpoint import load_checkpoint
from freeform.config import compose
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.records import EpochRecord, read_record, write_record
from freeform.run.build import control_bodies

ROD = np.zeros((3, 3, 3), np.uint8)
ROD[:, 1, 0] = (1, 2, 3)  # passive, muscle A, muscle B along x: two actuated voxels
CUBE = np.zeros((3, 3, 3), np.uint8)
CUBE[:2, :2, :2] = 2


def tiny_control(bodies: Path, *overrides: str) -> list[str]:
    """A control run of a second or two: two bodies repeated over 4 envs, 4 control steps an episode."""
    values = {"experiment": "control_steering_cpu", "control.bodies": str(bodies), "env.num_envs": 4,
              "control.burn_in": 0.01, "control.duration": 0.05, "agent.hidden": 4, "agent.sgd_minibatch_size": 8,
              "trainer.progress": "false", "trainer.print_every": 0, "trainer.threads": 1, "trainer.render_every": 0,
              "trainer.checkpoint_every": 1, "sim.precision": "f64"}
    for override in overrides:
        key, value = override.split("=", 1)
        values[key] = value
    return [f"{k}={v}" for k, v in values.items()]


@pytest.fixture
def bodies(tmp_path: Path) -> Path:
    path = tmp_path / "bodies.npy"
    np.save(path, np.stack([ROD, CUBE]))
    return path


def test_the_command_line_trains_a_controller_and_records_its_episodes(bodies: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    run = tmp_path / "run"
    run_cli(monkeypatch, *tiny_control(bodies, "trainer.epochs=2", "trainer.render_every=2"), f"hydra.run.dir={run}")
    record = read_record(run / "records" / "epoch_000001.npz")
    # the bodies, repeated in turn; one episode per env an epoch; no actions kept (trainer.record_actions=false)
    np.testing.assert_array_equal(record.final_grids, np.stack([ROD, CUBE, ROD, CUBE]))
    assert record.actions.shape == (4, 4, 0) and record.values.shape == (4, 4)
    assert np.isfinite(record.rewards).all() and record.metrics["volume"].tolist() == [3, 8, 3, 8]
    curves = scalars(run)
    assert [s for s, _ in curves["charts/episode_reward_mean"]] == [16, 32]  # 4 envs x 4 steps an epoch
    ckpt = load_checkpoint(run / "checkpoints" / "last.pt")
    assert ckpt["config"]["control"]["headings"] == "random" and ckpt["ppo"]["env"]["episode"] == 2
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run), size_guidance={"images": 0})
    events.Reload()
    assert "bodies/controlled_gait" in events.Tags()["images"]  # rendered at epoch 0 (render_every=2)


def test_two_epochs_equal_one_plus_resume_one_bit_for_bit(bodies: Path, tmp_path: Path) -> None:
    """Random headings (the episode count is the env's random state) and reward_norm (running statistics)."""
    straight_and_resumed(compose(*tiny_control(bodies, "seed=3")), tmp_path, epochs=2)
    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")["ppo"]
    b = load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")["ppo"]
    for name, tensor in a["policy"].items():
        assert torch.equal(tensor, b["policy"][name]), name
    assert torch.equal(a["return_rms"]["var"], b["return_rms"]["var"])
    ra, rb = (read_record(tmp_path / d / "records" / "epoch_000001.npz") for d in ("straight", "split"))
    np.testing.assert_array_equal(ra.rewards, rb.rewards)
    np.testing.assert_array_equal(ra.values, rb.values)
    # and the run's directory reads back as its controller, with the episode's config (evaluate --bodies reads it)
    from freeform.agents.controller_file import read_controller

    saved = read_controller(tmp_path / "split")
    assert saved.kind == "conv" and saved.control.headings == "random" and saved.sim is not None
    assert saved.controller.state_dict().keys() == a["policy"].keys()
    assert all(torch.equal(v, a["policy"][k]) for k, v in saved.controller.state_dict().items())


@pytest.mark.parametrize("kind, privileged", [("context", False), ("attention", False), ("context", True),
                                            ("context_gru", False)])
def test_the_app_trains_each_controller_kind_and_resumes_it_bit_for_bit(kind: str, privileged: bool, bodies: Path,
                                                                        tmp_path: Path) -> None:
    """control.controller picks the registry's kind (build_controller); two epochs equal one plus a resumed one.
    control.privileged_critic: the same controller inside a PrivilegedCritic, whose actor a controller.pt keeps."""
    overrides = (f"control.controller={kind}", "seed=1", f"control.privileged_critic={str(privileged).lower()}")
    straight_and_resumed(compose(*tiny_control(bodies, *overrides)), tmp_path, epochs=2)
    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")
    b = load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")
    from freeform.agents.controller_file import read_controller
    from freeform.agents.networks.controllers import CONTROLLERS

    kwargs = a["policy_kwargs"]["controller"] if privileged else a["policy_kwargs"]
    name = "PrivilegedCritic" if privileged else CONTROLLERS[kind].__name__
    assert a["policy_class"].endswith(":" + name) and kwargs["hidden"] == 4
    for key, tensor in a["ppo"]["policy"].items():
        assert torch.equal(tensor, b["ppo"]["policy"][key]), key
    saved = read_controller(tmp_path / "straight")  # the actor alone, acting on the sensed channels
    assert saved.kind == kind and not saved.control.privileged_critic
    prefix = "controller." if privileged else ""
    assert all(torch.equal(v, a["ppo"]["policy"][prefix + k]) for k, v in saved.controller.state_dict().items())
    if privileged:  # the critic's own part learnt something in two epochs (it starts at zero)
        assert a["ppo"]["policy"]["critic_head.2.weight"].abs().max() > 0


def test_headings_are_drawn_per_episode_and_environment_whatever_the_slice() -> None:
    """A data-parallel rank holding environments 2, 3 draws what one process draws for them, episode after episode."""
    grids = np.stack([ROD, CUBE, ROD, CUBE])
    control = ControlConfig(burn_in=0.0, duration=0.025, headings="random")
    whole, part = ControlEnv(grids, control=control, seed=7), ControlEnv(grids[2:], control=control, seed=7, first_env=2)
    for _ in range(3):
        whole.reset(), part.reset()
        np.testing.assert_array_equal(whole.heading[2:], part.heading)
        assert len(set(whole.heading.tolist())) == 4
    whole.step(torch.zeros(4, whole.action_dim))
    with pytest.raises(ValueError, match="multiple of the episode's 2 steps"):
        whole.state_dict()


def test_bodies_from_a_design_record_are_its_best(tmp_path: Path) -> None:
    grids = np.stack([ROD, CUBE, CUBE * 0 + (np.arange(27).reshape(3, 3, 3) == 13).astype(np.uint8)])
    path = write_record(tmp_path, EpochRecord(
        epoch=4, global_step=0, actions=np.zeros((3, 1, 7), np.float32), final_grids=grids,
        rewards=np.array([0.5, 2.0, 1.0], np.float32), values=np.zeros((3, 1), np.float32)))
    cfg = compose(*tiny_control(path, "control.top=2", "env.num_envs=3"))
    np.testing.assert_array_equal(control_bodies(cfg).numpy(), grids[[1, 2, 1]])


@pytest.mark.parametrize("override, message", [
    ("algo=ga", r"algo\.name must be ppo or distill in a control run"),
    ("agent.rollout_steps=6", r"agent\.rollout_steps must be a multiple of the control episode's 4 steps"),
    ("control.controller=rnn", r"control\.controller must be one of \['conv', 'mlp', 'context', 'attention', 'context_gru', 'attention_gru', 'attention_hyper'\]"),
    ("agent.obs_norm=true", r"agent\.obs_norm must be false in a control run"),
    ("control.stroke_periods=2", r"control\.head must be one of \['stroke', 'wave'\] exactly when control\.stroke_periods >= 1"),
    ("control.stroke_periods=-1", r"control\.stroke_periods must be an int >= 0"),
])
def test_a_bad_control_run_is_refused_naming_the_key(bodies: Path, override: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        compose(*tiny_control(bodies, override))


def test_bad_bodies_are_refused_naming_the_file(tmp_path: Path) -> None:
    missing = compose(*tiny_control(tmp_path / "nowhere.npy"))
    with pytest.raises(ValueError, match="no file"):
        control_bodies(missing)
    floats = tmp_path / "floats.npy"
    np.save(floats, ROD.astype(np.float32))
    with pytest.raises(ValueError, match=r"must hold uint8 grids"):
        control_bodies(compose(*tiny_control(floats)))
    empty = tmp_path / "empty.npy"
    np.save(empty, np.stack([ROD, ROD * 0]))
    with pytest.raises(ValueError, match=r"empty grids \(no voxel\) at \[1\]"):
        control_bodies(compose(*tiny_control(empty)))


def test_the_open_loop_figure_along_a_heading_is_the_gait_projected_on_it() -> None:
    """Three copies of one body (a batch gives each robot its solo result): along 0, π/2 and π its open-loop move is
    its x, its y and minus its x displacement."""
    from freeform.envs.control import open_loop_displacement
    from freeform.sim import SimConfig

    sim, control = SimConfig(precision="f64"), ControlConfig(burn_in=0.05, duration=0.25)
    three = np.stack([ROD] * 3)
    along_x = open_loop_displacement(three, sim, control)
    moved = open_loop_displacement(three, sim, control, headings=np.array([0.0, np.pi / 2, np.pi]))
    assert along_x[0] == moved[0] and abs(along_x[0]) > 1e-4  # it moves
    assert moved[2] == pytest.approx(-moved[0], rel=1e-9, abs=1e-12)
    assert moved[1] != moved[0]
    planar = open_loop_displacement(three, sim, control, planar=True)  # Pythagoras on the x and y moves
    assert planar == pytest.approx(np.hypot(moved[0], moved[1]), rel=1e-9)


# Data parallel: two gloo ranks holding environments 0-2 and 3-4 of a steering batch train what one process trains.
DP_ENVS = 5
DP_CONTROL = ControlConfig(burn_in=0.01, duration=0.05, headings="random")


def _dp_ppo(envs: tuple[int, int]):
    from freeform.agents import PPO, ConvController, PPOConfig
    from freeform.sim import SimConfig

    torch.manual_seed(0)
    grids = np.stack([ROD, CUBE, ROD, CUBE, ROD])[envs[0]:envs[1]]
    env = ControlEnv(grids, sim=SimConfig(precision="f64"), control=DP_CONTROL, seed=5, first_env=envs[0], box=(3, 3, 3))
    policy = ConvController.for_env(env, hidden=4)
    return PPO(env, policy, PPOConfig(rollout_steps=DP_CONTROL.steps, num_sgd_iter=2, sgd_minibatch_size=6, seed=3,
                                      lr=3e-3, reward_norm=True))


def _dp_worker(rank: int, world: int, init_file: str, out_dir: str) -> None:
    import os

    import torch.distributed as dist

    from freeform.agents.distributed import env_slice

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        ppo = _dp_ppo(env_slice(DP_ENVS, world, rank))
        stats = [ppo.train_epoch(), ppo.train_epoch()]
        rewards = ppo.dp.gather_envs(ppo.rollout.rewards, dim=1)
        torch.save({"stats": stats, "rewards": rewards, "heading": ppo.dp.gather_envs(
            torch.from_numpy(ppo.env.heading), dim=0), "params": torch.cat([p.detach().reshape(-1)
                                                                          for p in ppo.policy.parameters()])},
                   Path(out_dir) / f"rank{rank}.pt")
        dist.barrier()
    finally:
        dist.destroy_process_group()
    os._exit(0)  # (as tests/test_distributed.py: native thread pools torn down at exit have aborted finished workers)


@pytest.mark.usefixtures("one_thread", "keep_global_rng")
@pytest.mark.slow
def test_two_gloo_ranks_steer_as_one_process(tmp_path: Path) -> None:
    import torch.multiprocessing as mp

    single = _dp_ppo((0, DP_ENVS))
    stats = [single.train_epoch(), single.train_epoch()]
    mp.spawn(_dp_worker, args=(2, str(tmp_path / "pg"), str(tmp_path)), nprocs=2, join=True)
    rank0 = torch.load(tmp_path / "rank0.pt", weights_only=False)
    # each rank drew its environments' headings of the single process, episode after episode ...
    np.testing.assert_array_equal(rank0["heading"].numpy(), single.env.heading)
    # ... so the second epoch's rewards (after one data-parallel update) and statistics are the single run's
    torch.testing.assert_close(rank0["rewards"], single.rollout.rewards, rtol=1e-4, atol=1e-6)
    for key in ("episode_reward_mean", "policy_loss", "value_loss", "approx_kl"):
        assert rank0["stats"][1][key] == pytest.approx(stats[1][key], rel=1e-4, abs=1e-6), key
    torch.testing.assert_close(rank0["params"], torch.cat([p.detach().reshape(-1) for p in single.policy.parameters()]),
                               rtol=1e-4, atol=1e-5)


def test_an_empty_grid_moves_zero_open_loop_and_the_others_keep_their_place() -> None:
    """(A co-design policy's designs may be empty: the empty one has no robot, and the bodies after it must not shift.)"""
    from freeform.envs.control import open_loop_displacement
    from freeform.sim import SimConfig

    sim, control = SimConfig(precision="f64"), ControlConfig(burn_in=0.05, duration=0.25)
    alone = open_loop_displacement(np.stack([ROD, CUBE]), sim, control)
    mixed = open_loop_displacement(np.stack([ROD, ROD * 0, CUBE]), sim, control, headings=np.zeros(3))
    np.testing.assert_array_equal(mixed, [alone[0], 0.0, alone[1]])
    assert open_loop_displacement(np.stack([ROD * 0]), sim, control).tolist() == [0.0]


def test_the_climb_preset_controls_bodies_on_its_slope(tmp_path: Path) -> None:
    """``experiment=control_climb_cpu``: the control env stands on the run's terrain. A passive-commanded rod holds
    still on flat ground and slides downhill (negative reward along +x, the uphill direction) on a 40° slope, past
    what friction holds."""
    from freeform.run.build import control_env

    np.save(tmp_path / "rod.npy", ROD)
    moved = {}
    for degrees in (0.0, 40.0):
        cfg = compose(*tiny_control(tmp_path / "rod.npy", "experiment=control_climb_cpu", f"sim.terrain.degrees={degrees}",
                                    "control.duration=0.25", "control.burn_in=0.05", "control.headings=fixed"))
        env = control_env(cfg, torch.device("cpu"), (0, 4), 0)
        env.reset()
        total = torch.zeros(4)
        for _ in range(env.control.steps):
            total += env.step(torch.zeros(4, env.action_dim))[1]
        moved[degrees] = total
    assert compose("experiment=control_climb_cpu").sim.terrain.kind == "slope"
    assert moved[0.0].abs().max() < 1e-3 and (moved[40.0] < -0.1).all()
