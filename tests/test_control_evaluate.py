"""Zero-shot evaluation of a saved controller on given bodies (``python -m lab.control --evaluate PATH
--bodies BODIES.npy``): the command end to end on three tiny bodies, and its refusals naming the body."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from experiments.common import read_rows as read_csv
from experiments.common import write_rows
from freeform.agents.controller_file import save_controller
from freeform.agents.networks.controller_heads import ControlInputs
from freeform.agents.networks.controllers import ContextConvController, MLPController
from freeform.envs.control import OBS_CHANNELS, ControlConfig, ControlEnv, open_loop_displacement
from freeform.envs.response import RESPONSE_CHANNELS
from freeform.sim import SimConfig
from lab.control import main
from lab.heldout import read_bodies

SHORT = ControlConfig(burn_in=0.01, duration=0.05)  # four control steps (open_loop_moves refuses a burn-in of 0)


def tiny_bodies() -> np.ndarray:
    """Three bodies of ρ = 3: a muscle pair (box 2 × 1 × 1), an L of three voxels (2 × 2 × 1), and a bar of two with
    a lone voxel apart from it (simulated as the bar: its largest component)."""
    g = np.zeros((3, 3, 3, 3), np.uint8)
    g[0, 0:2, 0, 0] = [2, 3]
    g[1, 0:2, 0, 0], g[1, 0, 1, 0] = [2, 1], 3
    g[2, 0:2, 0, 0], g[2, 2, 2, 2] = [3, 2], 1
    return g


def test_the_evaluate_command_scores_every_body_against_its_open_loop_gait(tmp_path) -> None:
    """A controller trained in a 2 × 1 × 1 box (here: saved untrained) evaluated on bodies needing 2 × 2 × 1: a row
    per body with its simulated voxels (counted by hand), its open-loop gait (along +x, as open_loop_displacement
    scores it on the bodies as simulated), finite controller figures; the summary's six rows and three paired
    differences; the fractions of bodies beyond their own gait."""
    torch.manual_seed(0)
    net = ContextConvController(ControlInputs(len(OBS_CHANNELS), (2, 1, 1), OBS_CHANNELS.index("actuated")), hidden=4,
                               log_std=-1.0)
    save_controller(tmp_path / "controller.pt", net, SHORT, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    main(["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "fixed",
          "--eval-episodes", "2", "--out", str(tmp_path / "eval")])
    rows = read_csv(tmp_path / "eval" / "bodies.csv")
    assert list(rows[0]) == ["body", "voxels", "actuated", "open_loop", "controller", "band99", "mean_command", "untrained",
                            "untrained_mean_command"]
    assert [(int(r["body"]), int(r["voxels"]), int(r["actuated"])) for r in rows] == [(0, 2, 2), (1, 3, 2), (2, 2, 2)]
    as_simulated = tiny_bodies()
    as_simulated[2, 2, 2, 2] = 0
    expected = open_loop_displacement(as_simulated, SimConfig(), SHORT)
    np.testing.assert_allclose([float(r["open_loop"]) for r in rows], expected, rtol=1e-6, atol=1e-9)
    assert all(np.isfinite(float(r["controller"])) and float(r["band99"]) >= 0 for r in rows)
    summary = read_csv(tmp_path / "eval" / "summary.csv")
    assert len(summary) == 11 and [r["n"] for r in summary] == ["3"] * 11
    assert summary[1]["what"].startswith("controller (context") and "mean command" in summary[2]["what"]
    assert "zeroed" in summary[3]["what"] and "untrained" in summary[4]["what"] and "mean command" in summary[5]["what"]
    np.testing.assert_allclose(float(summary[0]["mean"]), expected.mean(), rtol=1e-6)
    np.testing.assert_allclose(float(summary[1]["mean"]), np.mean([float(r["controller"]) for r in rows]), rtol=1e-6)
    # the paired rows: per-body differences, recomputed from the body rows (mean command - own gait, stochastic -
    # untrained), so their band is the spread of the differences, not of the bodies
    for row, (a, b) in ((summary[6], ("mean_command", "open_loop")), (summary[7], ("controller", "untrained")),
                        (summary[8], ("mean_command", "untrained_mean_command"))):
        diff = np.array([float(r[a]) - float(r[b]) for r in rows])
        assert row["what"].startswith("paired")
        np.testing.assert_allclose(float(row["mean"]), diff.mean(), rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(float(row["band99"]), stats.t.ppf(0.995, 2) * diff.std(ddof=1) / np.sqrt(3),
                                   rtol=1e-6, atol=1e-9)  # (paired per body: Student's t over the 3 bodies)
    # the fraction of bodies the controller moves beyond their own gait (the "≥ 90 % of bodies")
    for row, key in ((summary[9], "controller"), (summary[10], "mean_command")):
        assert row["what"].startswith("fraction of bodies beyond their own gait")
        beyond = [float(r[key]) > float(r["open_loop"]) for r in rows]
        np.testing.assert_allclose(float(row["mean"]), np.mean(beyond), rtol=1e-9)


def test_malformed_bodies_are_refused_naming_the_body(tmp_path) -> None:
    bodies = tiny_bodies()
    for name, change, message in (
        ("material", lambda g: g.__setitem__((1, 1, 1, 1), 7), r"body 1 holds material \[7\], and the materials are 0 \(empty\), 1 \(passive\) … 3"),
        ("empty", lambda g: g.__setitem__(2, 0), "body 2 is empty"),
    ):
        bad = bodies.copy()
        change(bad)
        np.save(tmp_path / f"{name}.npy", bad)
        with pytest.raises(ValueError, match=message):
            read_bodies(tmp_path / f"{name}.npy", 3)
    np.save(tmp_path / "shape.npy", bodies[:, :, :2])
    with pytest.raises(ValueError, match=r"must be non-empty cubes \[M, ρ, ρ, ρ\], got shape \[3, 3, 2, 3\]"):
        read_bodies(tmp_path / "shape.npy", 3)
    np.save(tmp_path / "float.npy", bodies.astype(np.float32))
    with pytest.raises(ValueError, match="an integer dtype"):
        read_bodies(tmp_path / "float.npy", 3)
    # an MLP fits its own box only: bodies that need a larger one are refused with the reason
    np.save(tmp_path / "bodies.npy", bodies)
    save_controller(tmp_path / "mlp.pt", MLPController(len(OBS_CHANNELS), (2, 1, 1), 2, (4,)), SHORT)
    with pytest.raises(ValueError, match=r"learnt each cell of its box \(2, 1, 1\) apart.*\(2, 2, 1\)"):
        main(["--evaluate", str(tmp_path / "mlp.pt"), "--bodies", str(tmp_path / "bodies.npy"), "--eval-episodes", "1",
              "--out", str(tmp_path / "eval")])


def test_a_recurrent_controller_without_memory_evaluates_as_its_feed_forward_twin(tmp_path) -> None:
    """Truth: ContextConvController. A RecurrentContextController given the same convolutions, context and heads,
    and whose memory enters nothing (its columns of the context and critic layers 0), is the same function of each
    observation: the evaluate command, which carries the recurrent state through the episode, gives the same rows.
    With the memory's weights back, the rows change (the state is carried and read)."""
    from freeform.agents.networks.controllers import RecurrentContextController

    torch.manual_seed(0)
    args = dict(inputs=ControlInputs(len(OBS_CHANNELS), (2, 1, 1), OBS_CHANNELS.index("actuated")), hidden=4,
                log_std=-1.0)
    twin = ContextConvController(**args)
    net = RecurrentContextController(**args, memory=3)
    with torch.no_grad():
        twin.actor.weight.normal_(std=0.5)
        for name in ("conv_in", "actor", "critic_out"):
            getattr(net, name).load_state_dict(getattr(twin, name).state_dict())
        net.conv.load_state_dict(twin.convs[0].state_dict())
        for mine, theirs in ((net.context, twin.contexts[0]), (net.critic_fc, twin.critic_fc)):
            mine.bias.copy_(theirs.bias)
            mine.weight.zero_()
            mine.weight[:, :8].copy_(theirs.weight)
    rows = {}
    for name, controller in (("twin", twin), ("gru", net)):
        save_controller(tmp_path / name / "controller.pt", controller, SHORT, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    with torch.no_grad():
        net.context.weight[:, 8:].normal_(std=2.0)
    save_controller(tmp_path / "gru_memory" / "controller.pt", net, SHORT, SimConfig())
    for name in ("twin", "gru", "gru_memory"):
        main(["--evaluate", str(tmp_path / name), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "fixed",
              "--eval-episodes", "2", "--out", str(tmp_path / f"eval_{name}")])
        rows[name] = np.array([(float(r["controller"]), float(r["mean_command"]))
                               for r in read_csv(tmp_path / f"eval_{name}" / "bodies.csv")])
    np.testing.assert_allclose(rows["gru"], rows["twin"], rtol=1e-5, atol=1e-7)
    assert np.abs(rows["gru_memory"] - rows["twin"]).max() > 1e-4


def test_the_population_summary_pools_every_set_per_seed(tmp_path) -> None:
    """Truth: numpy on the same per-body values, pooled over the three sets: the means, the paired difference's
    99 % band (Student's t, n − 1: t · sd / √n), the ratio to the open loop and the count of bodies beyond their gait; a results
    folder missing a set's table for a seed leaves that seed out."""
    from lab import control_population as cp

    rng = np.random.default_rng(0)
    pooled = []
    for name, n in zip(cp.SETS, (3, 4, 2), strict=True):
        values = rng.uniform(0.0, 1.0, size=(n, len(cp.COLUMNS)))
        pooled.append(values)
        with open(tmp_path / f"seed0_{name}_bodies.csv", "w") as f:
            f.write("body," + ",".join(cp.COLUMNS) + "\n")
            f.writelines(f"{i}," + ",".join(str(v) for v in row) + "\n" for i, row in enumerate(values))
    (tmp_path / "seed1_grown_bodies.csv").write_text((tmp_path / "seed0_grown_bodies.csv").read_text())
    assert cp.seeds_in(tmp_path) == [0]
    row = cp.all_sets_row(tmp_path, 0)
    v = {c: np.concatenate(pooled)[:, i] for i, c in enumerate(cp.COLUMNS)}
    assert row["bodies"] == 9
    np.testing.assert_allclose(row["mean_command"], v["mean_command"].mean())
    diff = v["mean_command"] - v["untrained_mean_command"]
    np.testing.assert_allclose(row["mean_command_minus_untrained_mean_command_band99"],  # (paired: Student's t)
                               stats.t.ppf(0.995, 8) * diff.std(ddof=1) / 3.0, rtol=1e-6)
    np.testing.assert_allclose(row["mean_command_over_open_loop"], v["mean_command"].mean() / v["open_loop"].mean())
    assert row["beyond_own_gait"] == int((v["mean_command"] > v["open_loop"]).sum())


def test_the_zoos_population_controllers_are_in_the_repository_and_load() -> None:
    """The zoo's two population controllers are in a fresh clone (``.gitignore`` ignores ``*.pt`` outside the zoo and
    the lab's results) and rebuild from their files alone: the flat one with its wave along x, the steering one with
    its wave in the heading's frame, each under its preset's task."""
    from freeform import zoo

    flat, steering = (zoo.load(name) for name in ("population", "population_steering"))
    for saved in (flat, steering):
        assert saved.kind == "context" and saved.controller.head == "wave" and saved.control.residual
    assert flat.control.headings == "any" and "heading_channels" not in flat.controller.wave
    assert steering.control.headings == "random" and steering.controller.wave["heading_channels"] == (11, 12)
    assert steering.controller.wave["k"] == 1.5 and flat.controller.wave["k"] == 1.0


def test_design_after_control_scores_a_controller_that_adds_nothing_as_the_open_loop_gait(tmp_path) -> None:
    """``ControlledLocomotionTask`` with a residual controller whose mean command is 0 everywhere (its actor zeroed)
    scores each body by its own sine gait — ``open_loop_displacement`` of the bodies as simulated, an independent
    simulation — and an empty body by 0; the run's sim must have the controller's materials."""

    from freeform.agents.controller_file import read_controller
    from freeform.envs import ControlledLocomotionTask
    from freeform.envs.control import RESIDUAL_CHANNELS

    control = replace(SHORT, residual=True)
    net = ContextConvController(ControlInputs(len(RESIDUAL_CHANNELS), (2, 2, 1), RESIDUAL_CHANNELS.index("actuated")),
                                hidden=4, log_std=-1.0)
    with torch.no_grad():
        for p in net.actor.parameters():
            p.zero_()
    save_controller(tmp_path / "controller.pt", net, control, SimConfig())
    task = ControlledLocomotionTask(read_controller(tmp_path), headings="fixed")
    grids = np.concatenate([tiny_bodies(), np.zeros((1, 3, 3, 3), np.uint8)])
    reward = task.reward(torch.from_numpy(grids))
    as_simulated = tiny_bodies()
    as_simulated[2, 2, 2, 2] = 0
    expected = open_loop_displacement(as_simulated, SimConfig(), control)
    assert reward.dtype == torch.float32 and reward.shape == (4,) and float(reward[3]) == 0.0
    assert np.abs(expected).min() > 1e-4  # (the gaits move: a score of 0 would not pass for them)
    np.testing.assert_allclose(reward[:3].numpy(), expected, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="materials"):
        ControlledLocomotionTask(read_controller(tmp_path), sim=SimConfig(materials=SimConfig().materials[:2]))


def test_the_app_refuses_design_after_control_without_a_controller() -> None:
    from freeform.config import compose
    from freeform.run.build import build_task

    cfg = compose("experiment=controlled_design_cpu", "~task.options.controller")
    with pytest.raises(ValueError, match="task.options.controller"):
        build_task(cfg, torch.device("cpu"))


def test_bodies_csv_counts_actuated_voxels_not_a_strokes_action_channels(tmp_path) -> None:
    """A stroke controller acts on two channels per muscle, (a, b); ``bodies.csv``'s ``actuated`` still counts the
    muscles (the voxels counted by hand: 2, 2, 2), not 4, 4, 4."""

    control = replace(SHORT, stroke_periods=1)
    torch.manual_seed(0)
    net = ContextConvController(ControlInputs(len(OBS_CHANNELS), (2, 2, 1), OBS_CHANNELS.index("actuated")), hidden=4, log_std=-1.0,
                                head="stroke")
    save_controller(tmp_path / "controller.pt", net, control, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    main(["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "fixed",
          "--eval-episodes", "1", "--out", str(tmp_path / "eval")])
    rows = read_csv(tmp_path / "eval" / "bodies.csv")
    assert [(int(r["voxels"]), int(r["actuated"])) for r in rows] == [(2, 2), (3, 2), (2, 2)]


def test_the_evaluate_command_adds_each_bodys_own_controller_and_the_fraction_reached(tmp_path) -> None:
    """--per-body 2 on three bodies: per-body controllers for the first two are trained by the app (a bank of two
    teachers with the controller's episode settings) into the cache, read back (not trained again) on a second
    call; bodies.csv's per_body is finite for bodies 0 and 1 and empty for body 2, and the summary's fraction is the
    controller's mean over those two bodies divided by theirs, recomputed from bodies.csv."""
    torch.manual_seed(0)
    net = ContextConvController(ControlInputs(len(OBS_CHANNELS), (2, 2, 1), OBS_CHANNELS.index("actuated")), hidden=4, log_std=-1.0)
    trained = replace(SHORT, headings="any")
    save_controller(tmp_path / "controller.pt", net, trained, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    cache = tmp_path / "cache"
    plain = ["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "any",
             "--eval-episodes", "2"]
    args = [*plain, "--per-body", "2", "--per-body-cache", str(cache),
            *[f"--per-body-set={o}" for o in ("control.controller_init=null", "control.head=direct",
                                              "agent.hidden=4", "trainer.epochs=1", "agent.rollout_steps=4",
                                              "trainer.threads=1")]]
    main([*args, "--out", str(tmp_path / "eval")])
    (run,) = cache.iterdir()
    stamp = (run / "checkpoints" / "last.pt").stat().st_mtime_ns
    main([*args, "--out", str(tmp_path / "again")])
    assert (run / "checkpoints" / "last.pt").stat().st_mtime_ns == stamp  # read from the cache
    # the cached controllers moved in the default simulator: a controller of another physics is refused naming the
    # field; one run by another schedule (how it runs, not what) is measured against them
    for name, sim in (("heavier", SimConfig(gravity=-1.0)), ("scheduled", SimConfig(schedule="robots"))):
        save_controller(tmp_path / name / "controller.pt", net, trained, sim)
    with pytest.raises(ValueError, match=r"another simulator .* sim\.gravity: -9\.81 in the cache, -1\.0 here"):
        main([args[0], str(tmp_path / "heavier"), *args[2:], "--out", str(tmp_path / "heavier_eval")])
    main([args[0], str(tmp_path / "scheduled"), *args[2:], "--out", str(tmp_path / "scheduled_eval")])
    assert (run / "checkpoints" / "last.pt").stat().st_mtime_ns == stamp
    rows = read_csv(tmp_path / "eval" / "bodies.csv")
    assert [r["per_body"] for r in rows][2] == "nan" and all(np.isfinite(float(r["per_body"])) for r in rows[:2])
    summary = {r["what"]: r for r in read_csv(tmp_path / "eval" / "summary.csv")}
    for how, mine, theirs in (("stochastic", "controller", "per_body"),
                              ("mean command", "mean_command", "per_body_mean_command")):
        fraction = next(v for k, v in summary.items() if k.startswith(f"fraction of per-body control ({how})"))
        expected = np.mean([float(r[mine]) for r in rows[:2]]) / np.mean([float(r[theirs]) for r in rows[:2]])
        np.testing.assert_allclose(float(fraction["mean"]), expected, rtol=1e-6)
        assert fraction["n"] == "2"
        beyond = next(v for k, v in summary.items() if k.startswith(f"fraction of bodies beyond their own gait: "
                                                                    f"per-body controllers ({how})"))
        expected = np.mean([float(r[theirs]) > float(r["open_loop"]) for r in rows[:2]])
        np.testing.assert_allclose(float(beyond["mean"]), expected)
        assert beyond["n"] == "2"
    assert read_csv(tmp_path / "again" / "bodies.csv") == rows  # the same episodes, the same controllers
    # the per-body groups share every draw with the others (common random numbers): the controller's and the
    # references' columns, stochastic ones included, are those of the same evaluation without them
    main([*plain, "--out", str(tmp_path / "alone")])
    alone = read_csv(tmp_path / "alone" / "bodies.csv")
    assert [{k: r[k] for k in a} for r, a in zip(rows, alone, strict=True)] == alone
    main([*args, f"--per-body-run={run}", "--out", str(tmp_path / "from_run")])  # the teacher run, named
    assert read_csv(tmp_path / "from_run" / "bodies.csv") == rows
    with pytest.raises(ValueError, match=r"--per-body-run .* another simulator .* sim\.gravity: -9\.81 in the teacher "
                                         r"run, -1\.0 here"):
        main([args[0], str(tmp_path / "heavier"), *args[2:], f"--per-body-run={run}", "--out", str(tmp_path / "z")])
    assert not (tmp_path / "z").exists()
    np.save(tmp_path / "others.npy", tiny_bodies()[::-1].copy())
    with pytest.raises(ValueError, match="not the first 2 bodies given"):
        main([*args[:3], str(tmp_path / "others.npy"), *args[4:], f"--per-body-run={run}", "--out", str(tmp_path / "x")])
    # a controller of another interface than the teachers' (they read the world's frame, no open-loop channel, act
    # period by period): refused naming the field, before anything is played or written
    for field, value in (("frame", "heading"), ("residual", True), ("stroke_periods", 1)):
        save_controller(tmp_path / field / "controller.pt", net, replace(trained, **{field: value}), SimConfig())
        with pytest.raises(ValueError, match=rf"control\.{field}: .* in the teacher run, {value!r} here"):
            main([args[0], str(tmp_path / field), *args[2:], f"--per-body-run={run}", "--out", str(tmp_path / "y")])
    assert not (tmp_path / "y").exists()
    # teachers of another task than the one evaluated (--headings random against teachers of any)
    with pytest.warns(UserWarning, match="trained for headings=any"), \
            pytest.raises(ValueError, match=r"control\.headings: 'any' in the teacher run, 'random' here"):
        main([*args[:5], "random", *args[6:], f"--per-body-run={run}", "--out", str(tmp_path / "y")])
    # ... but teachers without the response channels drive an evaluation with them (a bank reads its own channels,
    # the first): the same per-body moves as without
    heard = ContextConvController(ControlInputs(len(OBS_CHANNELS) + len(RESPONSE_CHANNELS), (2, 2, 1),
                                                OBS_CHANNELS.index("actuated")), hidden=4, log_std=-1.0)
    save_controller(tmp_path / "heard" / "controller.pt", heard, replace(trained, response=True), SimConfig())
    main([args[0], str(tmp_path / "heard"), *args[2:], f"--per-body-run={run}", "--out", str(tmp_path / "heard_eval")])
    own = [r["per_body_mean_command"] for r in read_csv(tmp_path / "heard_eval" / "bodies.csv")]
    assert own == [r["per_body_mean_command"] for r in rows]


def test_the_per_body_cache_key_of_a_run_made_before_a_field_existed_still_finds_it() -> None:
    """The per-body cache is named by the bodies and the overrides of the episode's settings. The key below is the
    one caches made before ``control.frame`` existed were named by, its override list written out by hand (every
    ControlConfig field of that time, at a student's values): fields added since (``frame``) stay out of the key at
    their default, so an old cache is found; at another value they enter it."""
    import hashlib

    from lab.heldout import PerBody, per_body_cache_run

    bodies = tiny_bodies()[:2]
    control = ControlConfig(headings="any", command_rate=26.0, residual=True, ramp=True, stroke_periods=20,
                            burn_in=1.0, response=False)
    per = PerBody(n=2, cache=Path("cache"))
    then = ["control.teachers=2", "env.num_envs=8", "control.period=0.0125", "control.duration=2.0",
            "control.burn_in=1.0", "control.headings=any", "control.command_rate=26.0", "control.residual=true",
            "control.ramp=true", "control.stroke_periods=20", "control.response=false"]
    key = hashlib.sha1(bodies.tobytes() + "|".join(["control_teachers_cpu", *then]).encode()).hexdigest()[:12]
    run, overrides = per_body_cache_run(bodies, per, control)
    assert run == Path("cache") / f"control_teachers_cpu_2_{key}" and overrides == then
    turned, overrides = per_body_cache_run(bodies, per, replace(control, frame="heading"))
    assert turned != run and "control.frame=heading" in overrides
    # how the cache's run is executed names no other cache (it continues with more threads); what it trains does
    threaded, overrides = per_body_cache_run(bodies, replace(per, overrides=("trainer.threads=2",)), control)
    assert threaded == run and overrides[-1] == "trainer.threads=2"
    longer, _ = per_body_cache_run(bodies, replace(per, overrides=("trainer.epochs=300",)), control)
    assert longer != run


def test_the_hand_set_wave_row_is_a_wave_head_with_nothing_learnt(tmp_path) -> None:
    """A wave-head controller whose learnt parts are zero is the hand-set wave itself: its mean command's column
    equals the hand-set wave's, body by body (deterministic episodes of the same bodies)."""

    from freeform.agents.networks.controller_heads import HandSetWave

    control = replace(SHORT, stroke_periods=1)
    env = ControlEnv(tiny_bodies(), control=control)
    net = ContextConvController.for_env(env, hidden=4, log_std=-1.0, head="wave", wave=HandSetWave(1.5, 1.2))
    with torch.no_grad():
        for layer in (net.actor, net.wave_k):
            layer.weight.zero_()
            layer.bias.zero_()
    save_controller(tmp_path / "controller.pt", net, control, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    main(["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "fixed",
          "--eval-episodes", "1", "--out", str(tmp_path / "eval")])
    rows = read_csv(tmp_path / "eval" / "bodies.csv")
    assert any(abs(float(r["mean_command"])) > 1e-4 for r in rows)  # (the wave moves them: 0 = 0 would pass)
    np.testing.assert_allclose([float(r["hand_set_wave"]) for r in rows], [float(r["mean_command"]) for r in rows],
                               rtol=1e-5, atol=1e-7)
    # a head that learnt something, played at gain 0 (--wave-gain), is the hand-set wave again; at its own gain not
    torch.manual_seed(0)  # (weights that move these short episodes measurably off the wave)
    with torch.no_grad():
        for layer in (net.actor, net.wave_k):
            layer.weight.normal_(std=0.5)
            layer.bias.normal_(std=0.5)
    save_controller(tmp_path / "controller.pt", net, control, SimConfig())
    for gain in ("0", "1"):
        main(["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "fixed",
              "--eval-episodes", "1", "--wave-gain", gain, "--out", str(tmp_path / f"gain{gain}")])
    at = {g: read_csv(tmp_path / f"gain{g}" / "bodies.csv") for g in ("0", "1")}
    np.testing.assert_allclose([float(r["mean_command"]) for r in at["0"]], [float(r["hand_set_wave"]) for r in rows],
                               rtol=1e-5, atol=1e-7)
    moved = max(abs(float(a["mean_command"]) - float(b["mean_command"])) for a, b in zip(at["0"], at["1"], strict=True))
    assert moved > 1e-3, moved
    assert json.loads((tmp_path / "gain0" / "run.json").read_text())["wave_gain"] == 0.0
    # the untrained controller plays at gain 1 whatever the trained one's gain; a file saved at a gain records it
    assert [r["untrained_mean_command"] for r in at["0"]] == [r["untrained_mean_command"] for r in at["1"]]
    from freeform.agents.networks.controllers import with_wave_gain

    save_controller(tmp_path / "g0" / "controller.pt", with_wave_gain(net, 0.0), control, SimConfig())
    main(["--evaluate", str(tmp_path / "g0"), "--bodies", str(tmp_path / "bodies.npy"), "--headings", "fixed",
          "--eval-episodes", "1", "--out", str(tmp_path / "file_gain0")])
    assert json.loads((tmp_path / "file_gain0" / "run.json").read_text())["wave_gain"] == 0.0
    assert [r["mean_command"] for r in read_csv(tmp_path / "file_gain0" / "bodies.csv")] == \
        [r["mean_command"] for r in at["0"]]


def test_pooled_sets_are_one_table_over_all_their_bodies(tmp_path) -> None:
    """Two sets of 1 and 2 bodies pooled: the fraction of per-body control is the mean over all three bodies
    divided by theirs (mean command: 1.0 / (5/3) = 0.6, not the mean of the sets' fractions, 0.583), the
    wave ratio likewise, the bodies beyond their gait counted over all; a set evaluated without per-body
    controllers on some bodies only, or with another seed, is refused, naming the folder; sets evaluated without
    them pool without the per-body rows (the mean command paired against the wave, Student's t from scipy) or
    take an earlier pooled table's (--per-body-from), a body whose own gait differs refused; the scaling curve refuses
    points pooled from other sets of bodies (by the sets recorded, else by the count)."""
    from lab.heldout import pool

    def write(name: str, bodies: list[dict], seed: int = 0, source: str = "sets/a.npy") -> Path:
        folder = tmp_path / name
        folder.mkdir()
        with open(folder / "bodies.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(bodies[0]))
            writer.writeheader()
            writer.writerows(bodies)
        (folder / "run.json").write_text(json.dumps({"controller": "c.pt", "kind": "context", "seed": seed,
                                                     "bodies": source}))
        return folder

    def body(i, gait, stoch, mean, wave, own, own_mean):
        return {"body": i, "open_loop": gait, "controller": stoch, "mean_command": mean, "hand_set_wave": wave,
                "per_body": own, "per_body_mean_command": own_mean}

    a = write("a", [body(0, 0.1, 0.5, 1.0, 0.5, 1.0, 2.0)])
    b = write("b", [body(0, 0.9, 0.5, 0.5, 0.5, 1.0, 1.0), body(1, 0.2, 0.5, 1.5, 1.0, 1.0, 2.0)])
    summary = {r["what"]: float(r["mean"]) for r in pool([a, b], tmp_path / "out")}
    assert summary["fraction of per-body control (stochastic)"] == pytest.approx(0.5)
    assert summary["fraction of per-body control (mean command)"] == pytest.approx(1.0 / (5.0 / 3.0))  # 0.6
    assert summary["controller (mean command) over the hand-set wave"] == pytest.approx(1.0 / (2.0 / 3.0))
    assert summary["fraction of bodies beyond their own gait: controller (stochastic)"] == pytest.approx(2 / 3)
    rows = read_csv(tmp_path / "out" / "bodies.csv")
    assert [Path(r["set"]).name for r in rows] == ["a", "b", "b"]
    c = write("c", [body(0, 0.1, 0.5, 1.0, 0.5, float("nan"), float("nan"))])
    with pytest.raises(ValueError, match=r"per-body values on some bodies only \(.*c has them on 0 of its 1 bodies\)"):
        pool([a, c], tmp_path / "out2")
    assert not (tmp_path / "out2").exists()
    d = write("d", [body(0, 0.1, 0.5, 1.0, 0.5, 1.0, 2.0)], seed=1)
    with pytest.raises(ValueError, match=r"--pool .*d: evaluated with other settings .*\['seed'\]"):
        pool([a, d], tmp_path / "out3")
    # sets evaluated without per-body controllers take theirs from an earlier pooled table of the same bodies (its
    # folder or its bodies CSV), matched set by set and checked by each body's own gait
    bare = [write("a_bare", [body(0, 0.1, 0.5, 0.5, 0.5, float("nan"), float("nan"))]),
            write("b_bare", [body(0, 0.9, 0.5, 1.0, 0.5, float("nan"), float("nan")),
                             body(1, 0.2, 0.5, 1.0, 1.0, float("nan"), float("nan"))])]
    # ... or pool without them (a steering table: no per-body reference), the mean command paired against the wave
    pool(bare, tmp_path / "plain")
    plain = {r["what"]: r for r in read_csv(tmp_path / "plain" / "summary.csv")}
    assert not any("per-body" in what for what in plain) and "per_body" not in read_csv(tmp_path / "plain" / "bodies.csv")[0]
    gain = np.array([0.0, 0.5, 0.0])  # mean command minus the wave, body by body
    paired = plain["paired per body: controller (mean command) minus the hand-set wave"]
    assert float(paired["mean"]) == pytest.approx(gain.mean())
    assert float(paired["band99"]) == pytest.approx(stats.t.ppf(0.995, 2) * gain.std(ddof=1) / np.sqrt(3))
    assert float(plain["controller (mean command) over the hand-set wave"]["mean"]) == pytest.approx(2.5 / 2.0)
    with pytest.raises(ValueError, match="a pooled table without per-body columns"):
        pool(bare, tmp_path / "out5", per_body_from=tmp_path / "plain")
    half = body(0, 0.1, 0.5, 1.0, 0.5, 1.0, 2.0)
    del half["per_body_mean_command"]
    with pytest.raises(ValueError, match=r"half_old: bodies.csv has one of \['per_body', 'per_body_mean_command'\]"):
        pool([write("half_old", [half])], tmp_path / "out5")
    for reference in (tmp_path / "out", tmp_path / "out" / "bodies.csv"):
        taken = {r["what"]: float(r["mean"]) for r in pool(bare, tmp_path / "taken", per_body_from=reference)}
        assert taken["fraction of per-body control (mean command)"] == pytest.approx((2.5 / 3) / (5.0 / 3.0))
        assert taken["per-body controllers (stochastic)"] == pytest.approx(1.0)
    moved = write("b_moved", [body(0, 0.9, 0.5, 1.0, 0.5, 1.0, 1.0), body(1, 0.35, 0.5, 1.0, 1.0, 1.0, 2.0)])
    with pytest.raises(ValueError, match=r"body 1 of .*b_moved walked its own gait 0.350000 here and 0.200000 there"):
        pool([bare[0], moved], tmp_path / "out4", per_body_from=tmp_path / "out")
    # another host's floating point moves a gait in its fourth digit: taken, and warned with the drift; a whole
    # set moved by a little more than that is refused (other episode settings)
    drifted = write("b_drift", [body(0, 0.9002, 0.5, 1.0, 0.5, 1.0, 1.0), body(1, 0.2001, 0.5, 1.0, 1.0, 1.0, 2.0)])
    with pytest.warns(UserWarning, match=r"b_drift: the bodies walked their own gaits within the floating point of "
                                         r"another host \(median \|Δ\| 1.5e-04, largest 2.0e-04"):
        pool([bare[0], drifted], tmp_path / "out6", per_body_from=tmp_path / "out")
    shifted = write("b_shift", [body(0, 0.93, 0.5, 1.0, 0.5, 1.0, 1.0), body(1, 0.23, 0.5, 1.0, 1.0, 1.0, 2.0)])
    with pytest.raises(ValueError, match=r"b_shift: the bodies walked their own gaits a median 0.0300 apart"):
        pool([bare[0], shifted], tmp_path / "out7", per_body_from=tmp_path / "out")
    with pytest.raises(ValueError, match=r"a pooled table of 1 sets is needed .* it holds 2"):
        pool([a], tmp_path / "out4", per_body_from=tmp_path / "out")
    # the scaling curve reads pooled tables: its columns are the pooled figures, points over other bodies refused
    from lab.student_scaling import main as scaling

    pool([b, a], tmp_path / "ba")
    scaling(["128=" + str(tmp_path / "ba"), "64=" + str(tmp_path / "out"), "--out", str(tmp_path / "scaling")])
    points = read_csv(tmp_path / "scaling" / "scaling.csv")
    assert [int(p["teachers"]) for p in points] == [64, 128] and int(points[0]["bodies"]) == 3
    for p in points:
        assert float(p["fraction_mean_command"]) == pytest.approx(0.6)
        assert float(p["over_wave"]) == pytest.approx(1.5)
        assert float(p["beyond_gait"]) == pytest.approx(2 / 3)  # (mean command 1.0, 0.5, 1.5 against 0.1, 0.9, 0.2)
    assert (tmp_path / "scaling" / "scaling.png").stat().st_size > 0
    pool([b], tmp_path / "b_alone")
    with pytest.raises(SystemExit, match="pools other sets"):
        scaling(["64=" + str(tmp_path / "out"), "128=" + str(tmp_path / "b_alone"), "--out", str(tmp_path / "x")])
    record = json.loads((tmp_path / "b_alone" / "run.json").read_text())  # a table pooled before sets were recorded
    (tmp_path / "b_alone" / "run.json").write_text(json.dumps({k: v for k, v in record.items() if k != "sets"}))
    with pytest.raises(SystemExit, match="different numbers of bodies"):
        scaling(["64=" + str(tmp_path / "out"), "128=" + str(tmp_path / "b_alone"), "--out", str(tmp_path / "x")])
    # the same count over another set of bodies: refused by the sets the pooled tables record
    e = write("e", [body(0, 0.1, 0.5, 1.0, 0.5, 1.0, 2.0)], source="elsewhere/grown.npy")
    pool([b, e], tmp_path / "be")
    with pytest.raises(SystemExit, match=r"be pools other sets than .*out \(\[\('a.npy', 2\), \('grown.npy', 1\)\]"):
        scaling(["64=" + str(tmp_path / "out"), "128=" + str(tmp_path / "be"), "--out", str(tmp_path / "x")])
    with pytest.raises(ValueError, match="TEACHERS an integer"):
        scaling(["many=" + str(tmp_path / "out"), "--out", str(tmp_path / "x")])
    # against rounds: the same columns under "rounds", in rounds.csv beside scaling.csv
    scaling(["--x", "rounds", "8=" + str(tmp_path / "ba"), "4=" + str(tmp_path / "out"), "--out", str(tmp_path / "scaling")])
    rounds = read_csv(tmp_path / "scaling" / "rounds.csv")
    assert [int(p["rounds"]) for p in rounds] == [4, 8] and "teachers" not in rounds[0]
    assert [Path(p["folder"]).name for p in rounds] == ["out", "ba"]  # (each label with its own folder)
    assert [p["fraction_mean_command"] for p in rounds] == [p["fraction_mean_command"] for p in points]
    assert (tmp_path / "scaling" / "rounds.png").stat().st_size > 0
    with pytest.raises(ValueError, match="ROUNDS an integer"):
        scaling(["--x", "rounds", "all=" + str(tmp_path / "out"), "--out", str(tmp_path / "x")])
    # against generations of iterated distillation: generations.csv, its own column
    scaling(["--x", "generations", "2=" + str(tmp_path / "ba"), "1=" + str(tmp_path / "out"),
             "--out", str(tmp_path / "scaling")])
    generations = read_csv(tmp_path / "scaling" / "generations.csv")
    assert [int(p["generations"]) for p in generations] == [1, 2] and "rounds" not in generations[0]
    assert (tmp_path / "scaling" / "generations.png").stat().st_size > 0


def test_adaptation_reads_the_start_at_zero_epochs_and_the_bank_after(tmp_path) -> None:
    """``lab.adaptation``: a 0-epoch point is the evaluated controller (the bank's start), a later point
    the per-body column; the paired difference between starts is per body (a 3-body example worked by hand:
    differences 0.5, 0.3, 0.1 -> mean 0.3, band t(0.995, 2)·0.2/√3); tables over other bodies or without per-body
    controllers after training are refused (a 0-epoch point needs none)."""
    from lab.adaptation import main

    def write(name: str, rows: list[tuple], per_body: bool = True) -> str:
        folder = tmp_path / name
        folder.mkdir()
        fields = ["body", "open_loop", "controller", "mean_command"] + (
            ["per_body", "per_body_mean_command"] if per_body else [])
        with open(folder / "bodies.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(fields)
            writer.writerows(r[:len(fields)] for r in rows)
        return str(folder)

    # body, gait, controller (stoch, mean), per-body after training (stoch, mean)
    student = write("s", [(0, 0.5, 1.0, 1.0, 2.0, 2.5), (1, 0.5, 0.2, 0.4, 1.5, 1.6), (2, 0.5, 0.3, 0.3, 1.0, 1.0)])
    population = write("p", [(0, 0.5, 0.1, 0.1, 1.5, 2.0), (1, 0.5, 0.1, 0.2, 1.2, 1.3), (2, 0.5, 0.1, 0.1, 0.9, 0.9)])
    out = tmp_path / "out"
    main(["--from", "student", f"0={student}", f"4={student}", "--from", "population", f"4={population}",
          "--out", str(out)])
    rows = read_csv(out / "adaptation.csv")
    assert [(r["start"], r["epochs"]) for r in rows] == [("student", "0"), ("student", "4"), ("population", "4")]
    assert float(rows[0]["stochastic"]) == pytest.approx(0.5) and float(rows[1]["stochastic"]) == pytest.approx(1.5)
    assert float(rows[0]["beyond_gait"]) == pytest.approx(1 / 3, abs=1e-4) and float(rows[2]["beyond_gait"]) == 1.0
    (pair,) = read_csv(out / "paired.csv")
    assert (pair["epochs"], pair["minus"], pair["of"]) == ("4", "population", "student")
    assert float(pair["stochastic"]) == pytest.approx(0.3, abs=1e-4)
    assert float(pair["stochastic_band99"]) == pytest.approx(stats.t.ppf(0.995, 2) * 0.2 / np.sqrt(3), abs=1e-4)
    assert (out / "adaptation.png").is_file()

    other = write("o", [(0, 0.5, 1, 1, 1, 1), (1, 0.5, 1, 1, 1, 1)])
    with pytest.raises(SystemExit):
        main(["--from", "student", f"4={student}", f"8={other}", "--out", str(tmp_path / "x")])
    with pytest.raises(ValueError, match="no per_body column"):
        main(["--from", "student", f"4={write('n', [(0, 0.5, 1, 1)], per_body=False)}", "--out", str(tmp_path / "y")])
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    # a 0-epoch point reads only the start's columns: a table without per-body ones serves (the same figures)
    bare = write("bare", [(0, 0.5, 1.0, 1.0), (1, 0.5, 0.2, 0.4), (2, 0.5, 0.3, 0.3)], per_body=False)
    main(["--from", "student", f"0={bare}", f"4={student}", "--out", str(tmp_path / "z")])
    assert read_csv(tmp_path / "z" / "adaptation.csv")[0]["stochastic"] == rows[0]["stochastic"]


def test_two_tables_compared_body_by_body(tmp_path) -> None:
    """``lab.paired``: A − B per body with Student's t band (scipy's, 2 degrees of freedom for 3 bodies),
    the fraction of bodies A moves further; a folder and a bodies CSV read alike; tables of other bodies (another
    count, or a body whose own gait differs: other bodies or other episode settings) refused naming the body; the
    same bodies from another host (gaits within its floating point) compared and warned."""
    from lab.paired import main as paired

    def write(name: str, gaits, stoch, mean, set_folder: str | None = None, set_file: str | None = None) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        where = set_folder or f"runs/eval_{name}_grown"
        rows = [{"set": where, "body": i, "open_loop": g, "controller": s_, "mean_command": m}
                for i, (g, s_, m) in enumerate(zip(gaits, stoch, mean, strict=True))]
        write_rows(folder / "bodies.csv", rows)
        if set_file is not None:  # (lab.heldout --pool's run.json: each set folder's bodies file)
            (folder / "run.json").write_text(json.dumps({"pooled": [where], "sets": [{"bodies": set_file, "n": 3}]}))
        return folder

    a = write("a", [0.1, 0.2, 0.3], [1.0, 1.2, 0.9], [1.5, 1.1, 1.0])
    b = write("b", [0.1, 0.2, 0.3], [0.8, 1.0, 1.0], [1.0, 1.0, 1.0])
    paired([str(a), str(b / "bodies.csv"), "--out", str(tmp_path / "ab.csv")])
    rows = {r["what"]: r for r in read_csv(tmp_path / "ab.csv")}
    d = np.array([0.2, 0.2, -0.1])
    assert float(rows["stochastic"]["a_minus_b"]) == pytest.approx(d.mean(), abs=1e-4)
    assert float(rows["stochastic"]["band99"]) == pytest.approx(stats.t.ppf(0.995, 2) * d.std(ddof=1) / np.sqrt(3),
                                                                abs=1e-4)
    assert float(rows["stochastic"]["a_further"]) == pytest.approx(2 / 3, abs=1e-4)
    assert float(rows["mean command"]["a_minus_b"]) == pytest.approx(0.2, abs=1e-4)
    assert float(rows["mean command"]["a"]) == pytest.approx(3.6 / 3, abs=1e-4)
    moved = write("moved", [0.1, 0.35, 0.3], [1, 1, 1], [1, 1, 1])
    with pytest.raises(SystemExit):  # (the command line: argparse's error, naming the body)
        paired([str(a), str(moved)])
    from lab.paired import compare

    with pytest.raises(ValueError, match=r"body \('grown', '1'\) of .*a is not body .* \(its own gait 0.200000 against "
                                         r"0.350000\)"):
        compare(a, moved)
    # the same bodies evaluated on another host (its floating point moves a gait in the fourth digit): compared, and
    # warned; a whole set moved by more than that is other episode settings, refused
    with pytest.warns(UserWarning, match=r"within the floating point of another host \(median \|Δ\| 1.0e-04"):
        assert compare(a, write("host", [0.1001, 0.2001, 0.3001], [1.0, 1.2, 0.9], [1.5, 1.1, 1.0]))[0]["a_minus_b"] == 0
    with pytest.raises(ValueError, match=r"the bodies walked their own gaits a median 0.0200 apart"):
        compare(a, write("settings", [0.12, 0.22, 0.32], [1, 1, 1], [1, 1, 1]))
    # ... set by set: one set of a pooled table moved as a whole is refused, however many bodies the others hold
    two = [{"set": f"runs/eval_{s_}", "body": i, "open_loop": 0.1 * (i + 1), "controller": 1, "mean_command": 1}
           for s_ in ("x_grown", "x_hand_built") for i in range(3)]
    write_rows(tmp_path / "two.csv", two)
    write_rows(tmp_path / "two_moved.csv", [dict(r, open_loop=r["open_loop"] + 0.02 * ("hand" in r["set"]))
                                             for r in two])
    with pytest.raises(ValueError, match=r"\(set built\): the bodies walked their own gaits a median 0.0200 apart"):
        compare(tmp_path / "two.csv", tmp_path / "two_moved.csv")
    (tmp_path / "summary.csv").write_text("what,n,mean\ncontroller,3,1.0\n")  # (the wrong file of a folder)
    with pytest.raises(ValueError, match=r"summary.csv: no \['body', 'open_loop', 'controller', 'mean_command'\]"):
        compare(a, tmp_path / "summary.csv")
    short = write("short", [0.1, 0.2], [1, 1], [1, 1])
    with pytest.raises(ValueError, match="holds 3 bodies and .*short 2"):
        compare(a, short)
    with pytest.raises(ValueError, match="no bodies.csv there"):
        compare(a, tmp_path / "nowhere")
    # where both pooled tables record their sets' files, those name the sets, whatever the folders are called
    # (a committed table's folder and a fresh run's); the same folder suffix over another file is another set
    fresh = write("fresh", [0.1, 0.2, 0.3], [1, 1, 1], [1, 1, 1], "runs/eval_mine_design_unseen",
                  "lab/results/heldout_bodies/design_unseen.npy")
    kept = write("kept", [0.1, 0.2, 0.3], [1, 1, 1], [1, 1, 1], "lab/results/x/student16_all32",
                 "lab/results/heldout_bodies/design_unseen.npy")
    assert compare(fresh, kept)[0]["a_minus_b"] == 0
    (tmp_path / "kept_bodies.csv").write_bytes((kept / "bodies.csv").read_bytes())  # (as the results keep a table:
    (tmp_path / "kept_run.json").write_bytes((kept / "run.json").read_bytes())      # <name>_bodies.csv, _run.json)
    assert compare(fresh, tmp_path / "kept_bodies.csv")[0]["a_minus_b"] == 0
    (kept / "run.json").write_text(json.dumps({"pooled": ["elsewhere"], "sets": [{"bodies": "design_unseen.npy"}]}))
    with pytest.raises(ValueError, match=r"body \('unseen', '0'\) of .*fresh is not body \('all32', '0'\)"):
        compare(fresh, kept)  # (a run.json that misses its rows' sets: the folders' names again)
    with pytest.raises(ValueError, match=r"body \('design_unseen.npy', '0'\) of .*fresh is not body \('grown.npy'"):
        compare(fresh, write("other", [0.1, 0.2, 0.3], [1, 1, 1], [1, 1, 1], "runs/eval_x_design_unseen",
                             "lab/results/heldout_bodies/grown.npy"))


def test_symmetrize_averages_the_controller_and_keeps_an_equivariant_one(tmp_path) -> None:
    """--symmetrize ground evaluates the controller averaged over the ground's turns and mirrors. Independent truth:
    the hand-set travelling wave, which along random headings in the world's frame turns with the heading, so its
    average is itself: saved as the controller, its mean command moves every body as the unaveraged one does and as
    the hand-set wave row; ``run.json`` and the summary say what was averaged; without --bodies it is refused."""
    from lab.heldout import hand_set_wave

    control = replace(SHORT, headings="random", stroke_periods=1, residual=True)
    env = ControlEnv(tiny_bodies()[:2], control=control)
    assert env.box == (2, 2, 1)
    save_controller(tmp_path / "controller.pt", hand_set_wave(env, None, None), control, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    args = ["--evaluate", str(tmp_path), "--bodies", str(tmp_path / "bodies.npy"), "--eval-episodes", "1"]
    main([*args, "--out", str(tmp_path / "plain")])
    main([*args, "--symmetrize", "ground", "--out", str(tmp_path / "averaged")])
    plain, averaged = (read_csv(tmp_path / d / "bodies.csv") for d in ("plain", "averaged"))
    moved = [float(r["mean_command"]) for r in averaged]
    np.testing.assert_allclose(moved, [float(r["mean_command"]) for r in plain], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(moved, [float(r["hand_set_wave"]) for r in averaged], rtol=1e-4, atol=1e-7)
    assert max(abs(m) for m in moved) > 1e-3
    torch.manual_seed(0)  # a controller that is not equivariant: averaged, it moves the bodies otherwise
    skewed = ContextConvController(ControlInputs.of(env, "stroke"), hidden=4, head="stroke")
    with torch.no_grad():  # (its actor starts near 0: commands worth averaging need weights of some size)
        for weight in skewed.actor.parameters():
            weight.normal_(0.0, 0.2)
    save_controller(tmp_path / "skewed.pt", skewed, control, SimConfig())
    skew = ["--evaluate", str(tmp_path / "skewed.pt"), *args[2:]]
    main([*skew, "--out", str(tmp_path / "skewed")])
    main([*skew, "--symmetrize", "ground", "--out", str(tmp_path / "skewed_averaged")])
    one, other = (read_csv(tmp_path / d / "bodies.csv") for d in ("skewed", "skewed_averaged"))
    for column in ("mean_command", "controller"):  # the trained controller's groups are averaged, ...
        assert max(abs(float(a[column]) - float(b[column])) for a, b in zip(one, other, strict=True)) > 1e-4
    for column in ("untrained", "untrained_mean_command", "hand_set_wave"):  # ... the references are not
        assert [a[column] for a in one] == [b[column] for b in other]
    assert json.loads((tmp_path / "averaged" / "run.json").read_text())["symmetrize"] == "ground"
    summary = [r["what"] for r in read_csv(tmp_path / "averaged" / "summary.csv")]
    assert "controller (context, averaged over the ground group, mean command)" in summary
    with pytest.raises(SystemExit):
        main(["--evaluate", str(tmp_path), "--symmetrize", "ground", "--out", str(tmp_path / "refused")])
    with pytest.raises(ValueError, match=r"--symmetrize=ground turns the way a body walks, and control.headings=fixed"):
        main([*args, "--headings", "fixed", "--symmetrize", "ground", "--out", str(tmp_path / "fixed")])


def test_a_rows_per_body_figure_is_its_own_bodys_teacher_played_alone(tmp_path) -> None:
    """Each body's per-body column is that body's teacher (``bank.member(i)``) driving it alone, by its mean command,
    in an env of its own — not another body's teacher: a bank of two whose second teacher is made another controller
    (its weights doubled), and each row checked against its own teacher and against the other's."""
    import shutil

    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint, save_checkpoint
    from freeform.control.play import play

    torch.manual_seed(0)
    net = ContextConvController(ControlInputs(len(OBS_CHANNELS), (2, 2, 1), OBS_CHANNELS.index("actuated")), hidden=4,
                                log_std=-1.0)
    control = replace(SHORT, headings="any", duration=0.25)  # (20 periods: long enough for the teachers to differ)
    save_controller(tmp_path / "controller.pt", net, control, SimConfig())
    np.save(tmp_path / "bodies.npy", tiny_bodies()[:2])
    args = ["--evaluate", str(tmp_path / "controller.pt"), "--bodies", str(tmp_path / "bodies.npy"), "--headings",
            "any", "--eval-episodes", "1", "--per-body", "2", "--per-body-cache", str(tmp_path / "cache"),
            *[f"--per-body-set={o}" for o in ("control.controller_init=null", "control.head=direct", "agent.hidden=4",
                                              "trainer.epochs=1", "agent.rollout_steps=20", "trainer.threads=1")]]
    main([*args, "--out", str(tmp_path / "trained")])
    (cached,) = (tmp_path / "cache").iterdir()
    run = tmp_path / "teachers"
    shutil.copytree(cached, run)
    payload = load_checkpoint(run / "checkpoints" / "last.pt")
    for name, weights in payload["ppo"]["policy"].items():
        if name.startswith("stacked."):
            weights[1] = 2.0 * weights[1]
    save_checkpoint(run / "checkpoints" / "last.pt", payload)
    main([*args, f"--per-body-run={run}", "--out", str(tmp_path / "eval")])
    rows = read_csv(tmp_path / "eval" / "bodies.csv")
    bank, grids = bank_from_checkpoint(payload, str(run)), torch.from_numpy(tiny_bodies()[:2])

    def alone(teacher: int, body: int) -> float:
        env = ControlEnv(grids[body: body + 1], sim=SimConfig(), control=control, seed=0, box=(2, 2, 1))
        member = bank.member(teacher).eval()
        return float(play(env, [("alone", member, False, False)], control.steps, seed=0).returns[0, 0])

    for body in (0, 1):
        own, other, row = alone(body, body), alone(1 - body, body), float(rows[body]["per_body_mean_command"])
        assert abs(row - own) < 1e-3 * abs(other - own), (row, own, other)  # (the batch's rounding, far below)
