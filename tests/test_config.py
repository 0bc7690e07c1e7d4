"""The typed config: composition of conf/, the paper presets against Table I, and clear failures on bad input."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from freeform.agents import PPOConfig
from freeform.config import (
    AgentConfig,
    TrainConfig,
    compose,
    flatten,
    from_container,
    ppo_config,
    to_container,
    validate,
)
from freeform.train import CONF_DIR, _resolver_hydra_subdir, _resolver_run_dir


def test_default_is_the_cpu_demo() -> None:
    cfg = compose()
    assert cfg.name == "volume_cpu"
    assert cfg.task.name == "volume" and cfg.task.materials == 2
    assert cfg.trainer.device == "cpu"


def test_paper_volume_preset_is_table_one() -> None:
    cfg = compose("experiment=paper_volume")
    assert (cfg.env.num_envs, cfg.env.steps, cfg.env.resolution, cfg.env.bundle_size) == (256, 100, 20, 2)
    assert cfg.env.num_envs * cfg.env.steps == 25_600  # the train batch of Table I
    assert (cfg.task.name, cfg.task.materials, cfg.agent.hidden) == ("volume", 2, 128)
    assert (cfg.agent.sgd_minibatch_size, cfg.agent.num_sgd_iter, cfg.trainer.epochs) == (128, 50, 500)
    assert (cfg.agent.lr, cfg.agent.gamma) == (1e-4, 0.99)
    # The paper's PPO semantics (spec ppo.md), unchanged by the preset.
    a = cfg.agent
    assert (a.gae_lambda, a.clip_param, a.kl_coeff, a.kl_target) == (1.0, 0.3, 0.2, 0.01)
    assert (a.vf_loss_coeff, a.vf_clip_param, a.entropy_coeff, a.grad_clip) == (1.0, 1e5, 0.0, None)
    assert (a.advantage_norm, a.value_clip, a.lr_schedule) == ("batch", "squared", "constant")
    assert ppo_config(cfg, device="cpu").rollout_steps == 100  # one episode per environment per epoch


def test_paper_locomotion_preset_is_table_one() -> None:
    cfg = compose("experiment=paper_locomotion")
    assert (cfg.env.num_envs, cfg.env.steps) == (128, 100)
    assert cfg.env.num_envs * cfg.env.steps == 12_800
    assert (cfg.task.name, cfg.task.materials, cfg.agent.hidden) == ("locomotion", 4, 256)
    assert (cfg.agent.sgd_minibatch_size, cfg.agent.num_sgd_iter, cfg.trainer.epochs) == (128, 10, 2500)
    assert (cfg.agent.lr, cfg.agent.gamma) == (1e-4, 0.99)


def test_command_line_overrides_win_over_the_preset() -> None:
    cfg = compose("experiment=paper_volume", "env.num_envs=8", "agent.lr=3e-4", "seed=7")
    assert (cfg.env.num_envs, cfg.agent.lr, cfg.seed) == (8, 3e-4, 7)


def test_agent_section_is_ppo_config() -> None:
    """One config: the agent section is PPOConfig itself (a subclass adding the network's width and trunk), not a copy."""
    assert issubclass(AgentConfig, PPOConfig)
    assert [f.name for f in dataclasses.fields(AgentConfig)] == [f.name for f in dataclasses.fields(PPOConfig)] + ["hidden", "trunk"]



def test_group_yaml_holds_only_what_differs_from_the_typed_defaults() -> None:
    """One source per value: a group file under conf/ sets a field only to something other than its dataclass
    default (a group's own ``name`` excepted), so a default is changed in one place. Files of the ``_global_``
    package are checked section by section against TrainConfig's."""
    import yaml

    from freeform.config import EnvConfig, TaskConfig, TrainerConfig
    from freeform.evolve.config import AlgoConfig

    restated: list[str] = []

    def check(values: dict, default: object, where: str) -> int:
        count = 0
        for key, value in values.items():
            own = getattr(default, key)
            if isinstance(value, dict) and dataclasses.is_dataclass(own):
                count += check(value, own, f"{where}.{key}")
            elif key != "name" and not isinstance(own, dict) and own == value:
                restated.append(f"{where}.{key}: {value!r}")
            count += 1
        return count

    schemas = {"agent": AgentConfig, "env": EnvConfig, "trainer": TrainerConfig, "algo": AlgoConfig, "task": TaskConfig}
    checked = 0
    for group, schema in schemas.items():
        for path in sorted((Path(CONF_DIR) / group).glob("*.yaml")):
            text = path.read_text()
            values = yaml.safe_load(text) or {}
            glob = "@package _global_" in text
            checked += check(values, TrainConfig() if glob else schema(), path.name)
    assert not restated, f"defaults restated in conf/: {restated}"
    assert checked >= 30


def test_agent_errors_name_the_dotted_key_in_one_style() -> None:
    with pytest.raises(ValueError, match=r"^agent\.lr must be > 0, got -1\.0$"):
        compose("agent.lr=-1")
    with pytest.raises(ValueError, match=r"^PPOConfig\.lr must be > 0, got -1$"):
        PPOConfig(lr=-1)
    with pytest.raises(ValueError, match=r"^agent\.hidden must be an int >= 1, got 0$"):
        compose("agent.hidden=0")


def test_agent_seed_and_device_default_to_the_runs() -> None:
    cfg = compose("seed=5", "agent.seed=9")
    assert ppo_config(cfg, device="cpu").seed == 9
    assert ppo_config(compose("seed=5"), device="cpu").seed == 5


def test_ppo_config_takes_seed_device_and_default_rollout() -> None:
    cfg = compose("seed=11", "env.steps=7")
    p = ppo_config(cfg, device="cpu")
    assert (p.seed, p.device, p.rollout_steps) == (11, "cpu", 7)
    assert p.num_sgd_iter == cfg.agent.num_sgd_iter and p.lr == cfg.agent.lr
    cfg.agent.rollout_steps = 3
    assert ppo_config(cfg, device=None).rollout_steps == 3


@pytest.mark.parametrize("override", ["agent.lrr=1", "env.nope=3", "trainer.epoch=3"])
def test_unknown_key_fails_naming_it(override: str) -> None:
    with pytest.raises((ConfigCompositionException, ConfigKeyError)) as info:
        compose(override)
    key = override.split("=")[0]
    assert key.split(".")[1] in str(info.value) or key in str(info.value.__cause__)


def test_wrong_type_fails_naming_the_key() -> None:
    with pytest.raises((ConfigCompositionException, ValidationError)) as info:
        compose("env.num_envs=abc")
    assert "env.num_envs" in str(info.value) + str(info.value.__cause__)


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("env.resolution=7", "env.resolution"),
        ("env.resolution=0", "env.resolution"),
        ("env.num_envs=0", "env.num_envs"),
        ("env.steps=0", "env.steps"),
        ("env.bundle_size=0", "env.bundle_size"),
        ("env.bundle_size=3", "env.bundle_size"),
        ("env.action_bound=0", "env.action_bound"),
        ("task.materials=1", "task.materials"),
        ("agent.lr=-1", "agent.lr"),
        ("agent.gamma=1.5", "agent.gamma"),
        ("agent.num_sgd_iter=0", "agent.num_sgd_iter"),
        ("agent.advantage_norm=sometimes", "agent.advantage_norm"),
        ("agent.hidden=0", "agent.hidden"),
        ("trainer.device=gpu", "trainer.device"),
        ("trainer.epochs=-1", "trainer.epochs"),
        ("trainer.checkpoint_every=-2", "trainer.checkpoint_every"),
        ("sim.reward=fastest", "sim.reward"),
    ],
)
def test_invalid_value_fails_naming_the_key(override: str, key: str) -> None:
    with pytest.raises(ValueError, match="^" + re.escape(key) + " must"):
        compose(override)


def test_designed_materials_must_all_be_simulated() -> None:
    """task.materials against sim.materials: a simulated task's designs may only use materials the physics has
    (k - 1 of them); the volume task simulates nothing, so any k goes there."""
    with pytest.raises(ValueError, match=r"^task\.materials must be <= len\(sim\.materials\) \+ 1 = 4 .*got 5$"):
        compose("experiment=locomotion_cpu", "task.materials=5")
    assert compose("experiment=locomotion_cpu", "task.materials=3").task.materials == 3
    assert compose("experiment=volume_cpu", "task.materials=5").task.materials == 5


def test_a_population_elite_is_checked_only_where_a_learner_keeps_one() -> None:
    """algo.elite is the GA's: a GA's elite must be fewer than its population; PPO over two environments keeps none."""
    with pytest.raises(ValueError, match=r"^algo\.elite must be an integer in \[0, env\.num_envs - 1 = 1\]"):
        compose("algo=ga", "env.num_envs=2", "algo.elite=2")
    assert compose("env.num_envs=2", "algo.elite=2").env.num_envs == 2


def test_valid_edge_values_pass() -> None:
    cfg = compose("env.resolution=2", "env.bundle_size=2", "trainer.device=cuda:1", "trainer.epochs=0")
    assert cfg.env.resolution == 2 and cfg.trainer.device == "cuda:1"


def test_container_round_trip() -> None:
    cfg = compose("experiment=paper_locomotion", "seed=3")
    data = to_container(cfg)
    assert from_container(data) == cfg
    flat = flatten(data)
    assert flat["env.num_envs"] == 128 and flat["agent.hidden"] == 256 and flat["seed"] == 3


def test_validate_rejects_a_bad_dataclass_too() -> None:
    cfg = TrainConfig()
    cfg.env.resolution = 5
    with pytest.raises(ValueError, match="env.resolution"):
        validate(cfg)


def test_run_dir_resolvers(tmp_path: Path) -> None:
    run = tmp_path / "runs" / "x" / "t0"
    (run / "checkpoints").mkdir(parents=True)
    assert _resolver_run_dir(None, "runs/a/b") == "runs/a/b"
    assert Path(_resolver_run_dir(str(run), "unused")) == run
    assert Path(_resolver_run_dir(str(run / "checkpoints" / "last.pt"), "unused")) == run
    assert Path(_resolver_run_dir(str(run / "checkpoints"), "unused")) == run
    assert _resolver_hydra_subdir(None) == ".hydra"
    assert _resolver_hydra_subdir(str(run)).startswith(".hydra/resume_")


def test_every_experiment_preset_composes_and_validates() -> None:
    """Every ``conf/experiment`` preset composes into a valid config named after its file: a key renamed or a value
    refused fails here, not in a user's run."""
    names = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))
    assert len(names) >= 20
    for name in names:
        assert compose(f"experiment={name}").name == name, name


@pytest.mark.slow
def test_every_preset_warm_start_is_a_committed_controller_of_the_kind_it_builds() -> None:
    """A preset's ``control.controller_init`` (the population controller, its steering twin, the distilled
    students) names a controller of the zoo, which ships in the wheel, holding the controller kind, width and hand-set
    wave the preset builds: a preset changed without its file (or a file replaced by another kind) fails here, not
    at a user's first epoch."""
    from freeform import zoo

    checked = 0
    for path in sorted((Path(CONF_DIR) / "experiment").glob("*.yaml")):
        cfg = compose(f"experiment={path.stem}")
        if cfg.control is None or cfg.control.controller_init is None:
            continue
        assert cfg.control.controller_init in zoo.names(), path.stem
        saved = zoo.load(cfg.control.controller_init)
        width = cfg.control.hidden if cfg.control.hidden is not None else cfg.agent.hidden
        kwargs = saved.controller.init_kwargs
        assert (saved.kind, kwargs["hidden"], kwargs["head"]) == (cfg.control.controller, width, cfg.control.head), \
            path.stem
        assert (kwargs["wave"]["k"], kwargs["wave"]["amplitude"], kwargs["wave"].get("gain", 1.0)) == \
            (cfg.control.wave_k, cfg.control.wave_amplitude, cfg.control.wave_gain), path.stem
        checked += 1
    assert checked >= 6


def test_a_section_the_experiment_leaves_empty_is_named_with_the_experiments_that_have_it() -> None:
    """``freeform-train control.bodies=...`` without a control experiment: Hydra would fail with an assertion about a
    ``NoneType`` root; the check names the section, the experiment and the presets that have one."""
    from freeform.run.cli import CONF_DIR, _empty_section_overrides, presets_with

    message = _empty_section_overrides(["control.bodies=my_body.npy"], CONF_DIR)
    assert message is not None and "experiment=volume_cpu has no control section" in message
    having = presets_with("control", CONF_DIR)
    # the presets with a control section, by hand (control_adapt_cpu's through its base, control_teachers_cpu)
    truth = [f"codesign_{n}_cpu" for n in ("locomotion", "population", "population_steering", "steering", "student",
                                           "student_steering")] + \
            [f"control_{n}_cpu" for n in ("adapt", "adapt_steering", "climb", "locomotion", "population", "population_steering",
                                          "steering", "student", "student_steering", "teachers", "teachers_steering")]
    assert having == truth
    assert "volume_cpu" not in having and "paper_locomotion" not in having
    assert all(name in message for name in truth)
    assert _empty_section_overrides(["experiment=control_teachers_cpu", "control.bodies=b.npy"], CONF_DIR) is None
    assert _empty_section_overrides(["agent.lr=1e-3"], CONF_DIR) is None
