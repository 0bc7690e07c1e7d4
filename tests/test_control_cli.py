"""``freeform-control``: evaluate, watch and fit through the command line, on tiny bodies; bad input refused in one
line, naming the fix, with nothing written."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from freeform import zoo
from freeform.agents.controller_file import save_controller
from freeform.agents.networks.controller_heads import ControlInputs
from freeform.agents.networks.controllers import ContextConvController, MLPController
from freeform.control.bodies import read_bodies
from freeform.control.cli import main
from freeform.envs.control import OBS_CHANNELS, ControlConfig
from freeform.sim import SimConfig

SHORT = ControlConfig(burn_in=0.01, duration=0.05)  # four control periods of 0.0125 s


def tiny_bodies() -> np.ndarray:
    """Three bodies of ρ = 3: a muscle pair, an L of three voxels, a bar of two (boxes up to 2 × 2 × 1)."""
    g = np.zeros((3, 3, 3, 3), np.uint8)
    g[0, 0:2, 0, 0] = [2, 3]
    g[1, 0:2, 0, 0], g[1, 0, 1, 0] = [2, 1], 3
    g[2, 0:2, 0, 0] = [3, 2]
    return g


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def short_controller(path: Path) -> Path:
    torch.manual_seed(0)
    net = ContextConvController(ControlInputs(len(OBS_CHANNELS), (2, 2, 1), OBS_CHANNELS.index("actuated")), hidden=4,
                               log_std=-1.0)
    return save_controller(path, net, SHORT, SimConfig())


def refused(argv: list[str], capsys: pytest.CaptureFixture, *needles: str) -> str:
    """Run ``argv``, which must end in ``freeform-control: error: ...`` naming every needle."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("freeform-control: error: ") and len(err.strip().splitlines()) == 1, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


@pytest.mark.slow
def test_bad_bodies_are_refused_naming_the_problem_and_nothing_is_written(tmp_path, capsys) -> None:
    from freeform.control.fit import BUDGET_EPOCHS, DEFAULT_ADAPT_EPOCHS, Fit

    controller, out = short_controller(tmp_path / "controller.pt"), tmp_path / "out"
    cases = {"float": (tiny_bodies().astype(np.float32), "integer dtype (uint8), and this one is float32"),
             "rank": (tiny_bodies()[0, 0], "rank 2"),
             "empty": (np.concatenate([tiny_bodies(), np.zeros((1, 3, 3, 3), np.uint8)]), "body 3 is empty"),
             "material": (np.where(tiny_bodies() == 3, 7, tiny_bodies()).astype(np.uint8), "material [7]")}
    for name, (grids, needle) in cases.items():
        np.save(tmp_path / f"{name}.npy", grids)
        for argv in (["evaluate", str(controller), str(tmp_path / f"{name}.npy"), "--out", str(out)],
                     ["watch", str(controller), str(tmp_path / f"{name}.npy"), "--out", str(out)],
                     ["fit", str(tmp_path / f"{name}.npy"), "--out", str(out)]):
            refused(argv, capsys, needle)
    (tmp_path / "text.npy").write_text("not an array")
    refused(["evaluate", "student", str(tmp_path / "text.npy"), "--out", str(out)], capsys, "not a .npy file")
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    refused(["evaluate", "nosuch", str(tmp_path / "bodies.npy"), "--out", str(out)], capsys,
            "no such checkpoint, controller.pt or run folder as 'nosuch', nor a controller of the zoo",
            "student, pool256_gen4")
    # a fixed-box controller (the MLP) and bodies that need a larger box
    save_controller(tmp_path / "mlp.pt", MLPController(len(OBS_CHANNELS), (2, 1, 1), 2, (4,)), SHORT)
    refused(["evaluate", str(tmp_path / "mlp.pt"), str(tmp_path / "bodies.npy"), "--out", str(out)], capsys,
            "learnt each cell of its box (2, 1, 1) apart", "(2, 2, 1)")
    # a candidate of another simulator than the zoo's
    other = zoo.load("student")
    other.sim.gravity = -5.0
    save_controller(tmp_path / "moon.pt", other.controller, other.control, other.sim)
    refused(["fit", str(tmp_path / "bodies.npy"), "--out", str(out), "--candidates", "student",
             str(tmp_path / "moon.pt")], capsys, "sim.gravity: -5.0")
    refused(["watch", str(controller), str(tmp_path / "bodies.npy"), "--out", str(out)], capsys, "--body I")
    # fit's adaptation and trials, refused before a trial is played: one copy (no baseline), no candidate of the
    # kind the adaptation trains, a task other than the candidates', several trial episodes where each is the same
    # or none, two of one name
    fit = ["fit", str(tmp_path / "bodies.npy"), "--out", str(out)]
    refused([*fit, "--copies", "1"], capsys, "--copies must be >= 2")
    refused([*fit, "--adapt-epochs", "0", "--curve-every", "2"], capsys, "trials alone have no curve")
    pop = zoo.load("population")  # (a context controller 8 wide: of no recipe's kind, whose are 32 and 16)
    narrow = ContextConvController.from_init_kwargs({**pop.controller.init_kwargs, "hidden": 8})
    save_controller(tmp_path / "narrow" / "controller.pt", narrow, pop.control, pop.sim)
    refused([*fit, "--candidates", str(tmp_path / "narrow" / "controller.pt")], capsys,
            "no candidate is of a kind the adaptation trains", "control_teachers_cpu: context controllers (16 wide",
            "candidate narrow is a context controller (8 wide")
    refused([*fit, "--headings", "random", "--candidates", "student"], capsys,
            "--headings random: candidate student plays headings 'any'", "student_steering, population_steering")
    refused([*fit, "--trial-episodes", "2"], capsys, "--trial-episodes 2", "every episode is the same")
    refused([*fit, "--headings", "random", "--trial-episodes", "0"], capsys, "--trial-episodes must be a whole number")
    refused([*fit, "--episodes", "3"], capsys, "--episodes 3", "every episode is the same")
    refused([*fit, "--adapt-seconds", "0"], capsys, "--adapt-seconds 0.0: a number of seconds > 0")
    refused([*fit, "--adapt-seconds", "60", "--adapt-epochs", "0"], capsys, "with --adapt-epochs > 0")
    assert [Fit(("student",), **k).adapt_epochs for k in ({}, {"adapt_seconds": 60.0},
                                                          {"adapt_seconds": 60.0, "adapt_epochs": 5})] == [
        DEFAULT_ADAPT_EPOCHS, BUDGET_EPOCHS, 5]
    refused([*fit, "--headings", "random", "--episodes", "0"], capsys, "--episodes must be a whole number")
    (tmp_path / "a").mkdir()
    (tmp_path / "b" / "a").mkdir(parents=True)
    for folder in (tmp_path / "a", tmp_path / "b" / "a"):
        save_controller(folder / "controller.pt", other.controller, zoo.load("student").control, zoo.load("student").sim)
    refused([*fit, "--candidates", str(tmp_path / "a" / "controller.pt"), str(tmp_path / "b" / "a" / "controller.pt")],
            capsys, "share a name")
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        refused(["watch", str(controller), str(tmp_path / "bodies.npy"), "--body", "0", "--out", str(out), "--video",
                 "mp4"], capsys, "pip install 'freeform[video]'")
    assert not out.exists()


def test_a_body_in_pieces_keeps_its_largest_piece_with_a_warning(tmp_path) -> None:
    grids = tiny_bodies()
    grids[2, 2, 2, 2] = 1  # (a lone voxel apart from the bar)
    np.save(tmp_path / "pieces.npy", grids)
    with pytest.warns(UserWarning, match=r"body 2 is in several pieces.*1 voxel\(s\) of the others dropped"):
        kept = read_bodies(tmp_path / "pieces.npy", 3)
    assert torch.equal(kept, torch.from_numpy(tiny_bodies()))


@pytest.mark.parametrize("fps, every, frames", [(80.0, 1, 5), (40.0, 2, 3), (27.0, 3, 3)])
def test_watch_draws_every_frame_at_the_rate_and_moves_as_evaluate_says(tmp_path, fps: float, every: int,
                                                                       frames: int) -> None:
    """The GIF holds a frame at the window's start, one every ``every`` control periods and one at its end (4 periods
    of 0.0125 s: 80 fps is every period, 40 fps every second one, 27 fps every third and the fourth); gait.json's
    move is evaluate's mean command for that body, to the bit (the same env: the file's bodies, one row each)."""
    controller = short_controller(tmp_path / "controller.pt")
    np.save(tmp_path / "bodies.npy", tiny_bodies())
    main(["evaluate", str(controller), str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "eval"),
          "--headings", "fixed", "--episodes", "2"])
    main(["watch", str(controller), str(tmp_path / "bodies.npy"), "--body", "1", "--out", str(tmp_path / "seen"),
          "--fps", str(fps), "--headings", "fixed"])
    figures = json.loads((tmp_path / "seen" / "gait.json").read_text())
    gif = Image.open(tmp_path / "seen" / "gait.gif")
    assert gif.n_frames == figures["frames"] == frames
    assert figures["fps"] == pytest.approx(1 / (every * SHORT.period))
    evaluated = rows(tmp_path / "eval" / "bodies.csv")
    assert figures["displacement"] == float(evaluated[1]["mean_command"])
    assert figures["open_loop"] == pytest.approx(float(evaluated[1]["open_loop"]), rel=1e-12)
    assert list(evaluated[0]) == ["body", "voxels", "open_loop", "mean_command", "stochastic", "stochastic_band99"]
    summary = {r["what"]: r for r in rows(tmp_path / "eval" / "summary.csv")}
    assert float(summary["mean_command"]["mean"]) == pytest.approx(np.mean([float(r["mean_command"]) for r in evaluated]))


def test_fit_on_two_bodies_keeps_the_best_trial_and_its_figure_is_what_evaluate_finds(tmp_path) -> None:
    """Each body's chosen controller is the argmax of its trials (or that one adapted, where adapting moved it
    further); its controller.pt, evaluated on its body.npy, moves it exactly the figure bodies.csv gives; the zoo's
    wave trial is the hand-set wave (evaluate's column from the untrained context controller, an independent
    construction)."""
    np.save(tmp_path / "bodies.npy", tiny_bodies()[:2])
    main(["fit", str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "fitted"), "--adapt-epochs", "1",
          "--copies", "2", "--curve-every", "1", "--candidates", "population", *zoo.TRIED])
    fitted = rows(tmp_path / "fitted" / "bodies.csv")
    curve = rows(tmp_path / "fitted" / "adaptation.csv")  # (before the epoch: the trials' choice; after: the bank)
    assert [int(r["epoch"]) for r in curve] == [0, 1] and float(curve[0]["seconds"]) < float(curve[1]["seconds"])
    chosen = [max(float(v) for k, v in r.items() if k.startswith("trial_")) for r in fitted]
    assert float(curve[0]["kept"]) == pytest.approx(np.mean(chosen), rel=1e-5)
    # (after the last epoch: what fit kept, each body played alone by its file — another batch, another path)
    assert float(curve[1]["kept"]) == pytest.approx(np.mean([float(r["mean_command"]) for r in fitted]), rel=1e-3)
    per_body = rows(tmp_path / "fitted" / "adaptation_bodies.csv")  # (the same points, body by body)
    assert [(int(r["epoch"]), int(r["body"])) for r in per_body] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert [float(r["kept"]) for r in per_body[:2]] == pytest.approx(chosen, rel=1e-5)
    # (each body starts from its best trial: every candidate here is of a kind some recipe trains — the population
    # controller, the first candidate, a context controller — and on these bodies a student wins, so one bank)
    assert [float(r["adapted"]) for r in per_body[:2]] == pytest.approx(chosen, rel=1e-3)
    for point in curve:
        mine = [r for r in per_body if r["epoch"] == point["epoch"]]
        assert all(r["seconds"] == point["seconds"] for r in mine)
        for what in ("adapted", "kept"):
            assert np.mean([float(r[what]) for r in mine]) == pytest.approx(float(point[what]), rel=1e-12)
    assert [list(r)[:5] for r in fitted] == [["body", "chosen", "mean_command", "controller_file", "seconds"]] * 2
    main(["evaluate", "student", str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "eval"), "--episodes", "1"])
    for row, evaluated in zip(fitted, rows(tmp_path / "eval" / "bodies.csv"), strict=True):
        trials = {k[len("trial_"):]: float(v) for k, v in row.items() if k.startswith("trial_")}
        assert list(trials) == ["population", *zoo.TRIED]
        best = max(trials, key=trials.get)
        begun = max(zoo.TRIED, key=trials.get)
        assert row["chosen"] in (best, f"{begun} + 1 epochs")
        assert trials["wave"] == pytest.approx(float(evaluated["hand_set_wave"]), rel=1e-3)
        assert trials["student"] == float(evaluated["mean_command"])  # (the same rows: one a body, by its block)
        body = tmp_path / "fitted" / f"body{row['body']}"
        main(["evaluate", row["controller_file"], str(body / "body.npy"), "--out", str(body / "eval"), "--episodes", "1"])
        assert float(rows(body / "eval" / "bodies.csv")[0]["mean_command"]) == float(row["mean_command"])
    with pytest.raises(SystemExit):  # a second fit into the same folder is refused, the first kept
        main(["fit", str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "fitted"), "--adapt-epochs", "0"])
    assert rows(tmp_path / "fitted" / "bodies.csv") == fitted


def test_fit_adapts_each_body_by_its_picks_recipe(tmp_path) -> None:
    """Two bodies whose best trials are of two kinds (measured: the population controller moves the muscle pair
    0.282 against pool256_gen4's 0.209, the L 0.845 against 0.891) adapt in two banks, one a recipe, each body's
    controller of its pick's kind; before the first epoch each bank moves its body as its trial did (each loaded
    its own body's pick), and what fit keeps is what evaluate finds. A budget of a microsecond a body
    (``--adapt-seconds``) stops the adaptation after its first epoch of the three allowed, measured after it."""
    from freeform.agents.controller_file import read_controller

    np.save(tmp_path / "bodies.npy", tiny_bodies()[:2])
    main(["fit", str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "fitted"), "--adapt-epochs", "3",
          "--adapt-seconds", "1e-6", "--copies", "2", "--curve-every", "2", "--candidates", "population",
          "pool256_gen4"])
    assert [r["epoch"] for r in rows(tmp_path / "fitted" / "adaptation.csv")] == ["0", "1"]
    fitted = rows(tmp_path / "fitted" / "bodies.csv")
    trials = [(float(r["trial_population"]), float(r["trial_pool256_gen4"])) for r in fitted]
    assert trials[0][0] > trials[0][1] and trials[1][1] > trials[1][0]
    start = [float(r["adapted"]) for r in rows(tmp_path / "fitted" / "adaptation_bodies.csv") if r["epoch"] == "0"]
    assert start == pytest.approx([trials[0][0], trials[1][1]], rel=1e-3)
    kinds = []
    for row, pick in zip(fitted, ("population", "pool256_gen4"), strict=True):
        assert row["chosen"] in (pick, f"{pick} + 1 epochs")
        kinds.append(read_controller(Path(row["controller_file"])).kind)
        body = tmp_path / "fitted" / f"body{row['body']}"
        main(["evaluate", row["controller_file"], str(body / "body.npy"), "--out", str(body / "eval"), "--episodes", "1"])
        assert float(rows(body / "eval" / "bodies.csv")[0]["mean_command"]) == float(row["mean_command"])
    assert kinds == [zoo.load("population").kind, zoo.load("pool256_gen4").kind]


def test_block_env_draws_the_episodes_after_the_figures_and_a_part_of_a_set_as_the_set_does() -> None:
    """``first_episode`` 1 gives each body the headings of the episodes after its first (what a steering trial plays:
    never the draw its figure is measured on), and ``among`` gives bodies taken from a set the headings they draw in
    the set's env (what each bank of an adaptation plays)."""
    from freeform.control.evaluate import block_env

    saved = zoo.load("student_steering")
    grids = torch.from_numpy(tiny_bodies())
    whole = block_env(grids, saved, saved.control, blocks=1, episodes=5)
    whole.reset()
    after = block_env(grids, saved, saved.control, blocks=2, episodes=4, first_episode=1)
    after.reset()
    later = whole.heading.reshape(3, 5)[:, 1:].reshape(-1)
    assert np.array_equal(after.heading, np.tile(later, 2)) and len(np.unique(whole.heading)) == 15
    part = block_env(grids[[2, 0]], saved, saved.control, blocks=1, episodes=5, among=(np.array([2, 0]), 3))
    part.reset()
    assert np.array_equal(part.heading, whole.heading.reshape(3, 5)[[2, 0]].reshape(-1))
    with pytest.raises(ValueError, match="among: 2 places in a set of 3"):
        block_env(grids[:2], saved, saved.control, blocks=1, among=(np.array([0, 3]), 3))


@pytest.mark.slow
def test_fit_for_steering_chooses_on_the_trial_episodes_and_reports_the_others(tmp_path) -> None:
    """``--headings random``: the zoo's steering candidates, each figure the mean of ``--episodes 2`` (evaluate's
    own episodes 0–1 of the candidate) and each trial the mean of the ``--trial-episodes 3`` after them (episodes
    2–4, played apart) — the pick's figure before the first epoch (what evaluate finds for it), what fit keeps after
    the last (what evaluate finds for the file written), so that no figure is measured on a draw that chose it. On
    these three bodies the two candidates each win (measured: the student body 2, the population controller the
    others), so two banks each play their bodies along the set's draws."""
    from freeform.control.evaluate import block_env
    from freeform.control.play import play

    grids = tiny_bodies()
    np.save(tmp_path / "bodies.npy", grids)
    main(["fit", str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "fitted"), "--headings", "random",
          "--adapt-epochs", "1", "--copies", "2", "--curve-every", "1", "--episodes", "2", "--trial-episodes", "3"])
    fitted = rows(tmp_path / "fitted" / "bodies.csv")
    assert [k for k in fitted[0] if k.startswith("trial_")] == [f"trial_{n}" for n in zoo.STEERING]
    first, kept, bank = {}, {}, {}
    for r in rows(tmp_path / "fitted" / "adaptation_bodies.csv"):
        (first if r["epoch"] == "0" else kept)[int(r["body"])] = float(r["kept"])
        if r["epoch"] == "0":
            bank[int(r["body"])] = float(r["adapted"])
    picks = [max(zoo.STEERING, key=lambda n: float(r[f"trial_{n}"])) for r in fitted]
    assert picks == ["population_steering", "population_steering", "student_steering"]
    for name in zoo.STEERING:
        saved = zoo.load(name)
        env = block_env(torch.from_numpy(grids), saved, saved.control, blocks=1, episodes=5)
        moves = play(env, [(name, saved.controller.eval(), False, False)], saved.control.steps, 0).returns[0]
        trial, figure = moves.reshape(3, 5)[:, 2:].mean(1), moves.reshape(3, 5)[:, :2].mean(1)
        assert [float(r[f"trial_{name}"]) for r in fitted] == pytest.approx(trial, rel=1e-3, abs=1e-4)
        main(["evaluate", name, str(tmp_path / "bodies.npy"), "--out", str(tmp_path / name), "--episodes", "2"])
        for i, r in enumerate(rows(tmp_path / name / "bodies.csv")):
            assert float(r["mean_command"]) == pytest.approx(figure[i], abs=1e-3)  # (another batch: rounding)
            if picks[i] == name:  # (before the first epoch: the pick, alone and in its bank)
                assert first[i] == pytest.approx(float(r["mean_command"]), abs=1e-3)
                assert bank[i] == pytest.approx(float(r["mean_command"]), abs=3e-3)  # (another heading: tenths)
    for i, row in enumerate(fitted):  # (a body's headings are its row's draws in the set: evaluate on the set, row i)
        body = tmp_path / "fitted" / f"body{i}"
        main(["evaluate", row["controller_file"], str(tmp_path / "bodies.npy"), "--out", str(body / "eval"),
              "--episodes", "2"])
        assert float(rows(body / "eval" / "bodies.csv")[i]["mean_command"]) == pytest.approx(
            float(row["mean_command"]), abs=1e-3)  # (a batch of two rows there, of one here: rounding)
        assert kept[i] == pytest.approx(float(row["mean_command"]), abs=1e-3)


def test_fit_set_reaches_the_adaptations_config_and_refuses_what_fit_sets_itself(tmp_path, capsys) -> None:
    """``--set agent.lr=5e-4`` is the adaptation's learning rate while fit's own keys stay fit's; the keys fit sets
    itself, a setting without '=', a value the config refuses and a key it lacks are refused before any trial, naming
    the fix, with nothing written."""
    from freeform.control.fit import Candidates, Fit, adaptation

    grids = torch.from_numpy(tiny_bodies()[:2])
    np.save(tmp_path / "bodies.npy", grids.numpy())
    how = Fit(("student",), adapt_epochs=3, copies=2, seed=7, settings=("agent.lr=5e-4", "agent.num_sgd_iter=2"))
    for cfg, plain in zip(adaptation(Candidates(how.candidates, grids), 2, how, tmp_path / "bodies.npy"),
                          adaptation(Candidates(how.candidates, grids), 2, Fit(("student",)), tmp_path / "bodies.npy"),
                          strict=True):  # (every recipe's)
        assert (cfg.agent.lr, cfg.agent.num_sgd_iter) == (5e-4, 2)
        assert (cfg.trainer.epochs, cfg.env.num_envs, cfg.control.teachers, cfg.seed) == (3, 4, 2, 7)
        assert cfg.agent.sgd_minibatch_size == plain.agent.sgd_minibatch_size
    fit = ["fit", str(tmp_path / "bodies.npy"), "--out", str(tmp_path / "out"), "--candidates", "student"]
    refused([*fit, "--set", "agent.lr=0"], capsys, "refuses it", "agent.lr must be > 0")
    refused([*fit, "--set", "agent.lr"], capsys, "--set 'agent.lr': give KEY=VALUE")
    refused([*fit, "--set", "trainer.epochs=3"], capsys, "fit sets trainer.epochs itself (give --adapt-epochs)")
    refused([*fit, "--set", "env.num_envs=8"], capsys, "give --copies")
    refused([*fit, "--set", "agent.nosuch=1"], capsys, "--set agent.nosuch=1", "refuses it", "nosuch")
    refused([*fit, "--set", "agent.seed=3"], capsys, "fit sets agent.seed itself (give --seed)")
    refused([*fit, "--set", "+trainer.epochs=3"], capsys, "fit sets trainer.epochs itself")
    refused([*fit, "--set", "~agent.lr"], capsys, "it deletes none")
    refused([*fit, "--set", "agent.lr=1e-3", "--adapt-epochs", "0"], capsys, "trials alone have no recipe")
    assert not (tmp_path / "out").exists()


def test_each_candidate_is_adapted_by_the_recipe_of_its_kind(tmp_path) -> None:
    """The zoo's students (the wave among them: the students' network with its learnt heads at zero) by the
    students' recipe, the population controller (a context controller, 16 wide) by the per-body teachers' (lr 1e-3:
    the reference's recipe); with the students' recipe alone the context controller is not adapted, and a fit whose
    candidates no recipe trains is refused naming the kind each recipe trains."""
    from freeform.control.fit import (
        RECIPES,
        STEERING_RECIPES,
        Candidates,
        Fit,
        adaptation,
        candidate_name,
        recipe_of,
    )

    assert [candidate_name(n) for n in ("library/d3", "student", "runs/mine/controller.pt", "runs/mine")] == [
        "library/d3", "student", "mine", "mine"]  # (a zoo name as it is, the library's members too)

    grids = torch.from_numpy(tiny_bodies()[:2])
    c = Candidates(("population", "student", "wave"), grids)
    cfgs = adaptation(c, 2, Fit(c.names), tmp_path / "bodies.npy")
    assert RECIPES == ("control_adapt_cpu", "control_teachers_cpu")
    assert recipe_of(c, cfgs).tolist() == [1, 0, 0]
    steering = Candidates(("population_steering", "student_steering"), grids)  # (their recipes, by the task)
    steer = adaptation(steering, 2, Fit(steering.names), tmp_path / "bodies.npy")
    assert [cfg.name for cfg in steer] == list(STEERING_RECIPES) and recipe_of(steering, steer).tolist() == [1, 0]
    assert {cfg.control.headings for cfg in steer} == {"random"}
    assert [cfg.agent.lr for cfg in cfgs] == [3e-4, 1e-3]
    alone = adaptation(c, 2, Fit(c.names, presets=RECIPES[:1]), tmp_path / "bodies.npy")
    assert recipe_of(c, alone).tolist() == [-1, 0, 0]
    context = Candidates(("population",), grids)
    with pytest.raises(ValueError, match="no candidate is of a kind the adaptation trains .*attention.*32 wide"):
        adaptation(context, 2, Fit(context.names, presets=RECIPES[:1]), tmp_path / "bodies.npy")


def test_each_body_adapts_its_best_adaptable_candidate_and_ties_go_to_the_earlier() -> None:
    from freeform.control.fit import chosen

    trial = np.array([[1.0, 5.0, 2.0], [3.0, 5.0, 0.5], [9.0, 0.0, 1.0]])  # [candidates, bodies]; the third not adaptable
    assert chosen(trial).tolist() == [2, 0, 0]
    assert chosen(trial, np.array([True, True, False])).tolist() == [1, 0, 0]


def test_zoo_lists_every_controller_once_and_the_library_as_one_line(capsys) -> None:
    """Every name a user can give is listed (the library by its range), each beside its card's first line."""
    main(["zoo"])
    lines = capsys.readouterr().out.splitlines()
    listed = [line.split()[0] for line in lines[:lines.index("")]]
    library = [line for line in lines if line.startswith(zoo.LIBRARY[0])]
    assert listed == [n for n in zoo.names() if n not in zoo.LIBRARY[1:]]
    assert len(library) == 1 and f"… {zoo.LIBRARY[-1]}" in library[0]
    assert "training bodies" in library[0]  # the library's own card, not a member's
    for line in lines[:lines.index("")]:
        name = line.split()[0]
        if name not in zoo.LIBRARY:
            first = next(x for x in zoo.card(name).splitlines() if x and not x.startswith("#"))
            assert line.endswith(first), name
    assert "`fit --headings random` student_steering, population_steering;" in lines[-1]  # (what each task tries)
