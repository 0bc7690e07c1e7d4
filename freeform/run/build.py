"""A run's objects from its config: the task and the learner from one registry each, the design env from one function.

    register_task("mine")(builder)        # task.name=mine: builder(cfg, device) -> a freeform.envs.Task
    register_learner("mine")(builder)     # algo.name=mine: builder(cfg, env, device, envs) -> a freeform.learner.Learner

(``LEARNERS`` and ``register_learner`` live in ``freeform.learner``, below the config that validates the names;
this module registers freeform's own.)

Every trajectory reward registered with ``freeform.envs.trajectory.trajectory_reward`` is a task of its name too.
"""

from __future__ import annotations

import csv
import json
import logging
import random
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch

from freeform.config import TrainConfig, ppo_config
from freeform.envs.base import Task, VecEnv
from freeform.envs.control_config import described_differences
from freeform.learner import LEARNERS, Learner, register_learner

if TYPE_CHECKING:
    from freeform.envs.control_config import ControlConfig
    from freeform.sim import SimConfig

TaskBuilder = Callable[[TrainConfig, torch.device], Task]
TASKS: dict[str, TaskBuilder] = {}
"""``task.name`` -> builder ``(cfg, device) -> Task``. Add one with :func:`register_task`."""



def register_task(name: str) -> Callable[[TaskBuilder], TaskBuilder]:
    """Decorator: make ``task.name=<name>`` build its task with the decorated function."""

    def decorate(builder: TaskBuilder) -> TaskBuilder:
        TASKS[name] = builder
        return builder

    return decorate


# ------------------------------------------------------------------------------------------------ tasks


def _simulator_options(cfg: TrainConfig, device: torch.device) -> dict[str, Any]:
    """A simulated task's constructor arguments: the run's ``sim`` and device, and the simulator's arch taken from
    the run's device (no silent CPU fallback under a GPU run: resolve_device checked CUDA); ``task.options`` win."""
    return {"sim": cfg.sim, "device": device, "arch": "cuda" if device.type == "cuda" else "cpu", **cfg.task.options}


@register_task("volume")
def _volume_task(cfg: TrainConfig, device: torch.device) -> Task:
    from freeform.envs import VolumeTask

    return VolumeTask(**cfg.task.options)


@register_task("locomotion")
def _locomotion_task(cfg: TrainConfig, device: torch.device) -> Task:
    from freeform.envs import LocomotionTask

    return LocomotionTask(**_simulator_options(cfg, device))


@register_task("controlled_locomotion")
def _controlled_locomotion_task(cfg: TrainConfig, device: torch.device) -> Task:
    from freeform.agents.controller_file import read_controller
    from freeform.envs import ControlledLocomotionTask

    if "controller" not in cfg.task.options:
        raise ValueError("task.name=controlled_locomotion needs task.options.controller=PATH (a controller.pt, a "
                         "folder holding one, or a control run's directory)")
    options = _simulator_options(cfg, device)

    controller = read_controller(controller_source(str(options["controller"])))
    return ControlledLocomotionTask(**{**options, "controller": controller})


def _trajectory_task(cfg: TrainConfig, device: torch.device) -> Task:
    """A ``TrajectoryTask`` of the reward registered as ``task.name`` (freeform/envs/trajectory.py)."""
    from freeform.envs import TrajectoryTask

    return TrajectoryTask(cfg.task.name, **_simulator_options(cfg, device))


def task_builders() -> dict[str, TaskBuilder]:
    """Every task name a run may give: the registered builders and every trajectory reward (the built-ins and a
    user's own, registered with ``trajectory_reward``), looked up when asked so that late registrations count."""
    from freeform.envs.trajectory import TRAJECTORY_REWARDS

    return {**dict.fromkeys(TRAJECTORY_REWARDS, _trajectory_task), **TASKS}


def build_task(cfg: TrainConfig, device: torch.device) -> Task:
    """The run's task from the registry, checked against the :class:`freeform.envs.Task` protocol."""
    builders = task_builders()
    if cfg.task.name not in builders:
        raise ValueError(f"task.name must be one of {sorted(builders)}, got {cfg.task.name!r}")
    task = builders[cfg.task.name](cfg, device)
    if not isinstance(task, Task):
        raise ValueError(f"task.name={cfg.task.name!r} built a {type(task).__name__}, which has no reward(final_grids)")
    return task


# ------------------------------------------------------------------------------------------------ env and learner


def resolve_device(name: str, experiment: str | None = None, cuda_graph: bool = False) -> torch.device:
    """``trainer.device`` -> a torch device (``auto``: CUDA when available, else CPU; ``cuda``: this process's
    current GPU, which is the rank's own under torchrun, see ``distributed.pin_local_gpu``).

    A run that asks for CUDA where there is none stops here with one line naming the override that runs it on the
    CPU anyway (the paper's GPU presets set ``trainer.device: cuda``, and ``agent.cuda_graph: true``, which the CPU
    has no use for: ``cuda_graph`` says so)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        what = f"experiment={experiment} is meant for a GPU (trainer.device={name})" if experiment else f"trainer.device={name}"
        cpu = "trainer.device=cpu agent.cuda_graph=false" if cuda_graph else "trainer.device=cpu"
        raise ValueError(f"{what} but no CUDA device is available here; add {cpu} to run it on the CPU anyway")
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return device


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch's global RNGs (the network's initialisation draws from torch's)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def design_env(cfg: TrainConfig, device: torch.device, num_envs: int, seed: int) -> Any:
    """The run's ``DesignEnv`` of ``num_envs`` environments seeded ``seed``, scoring with a task of its own."""
    from freeform.envs import DesignEnv

    return DesignEnv(num_envs, cfg.env,
                     materials=cfg.task.materials, task=build_task(cfg, device), device=device, seed=seed)


def control_bodies(cfg: TrainConfig, arch: str = "cpu") -> torch.Tensor:
    """A control run's bodies, uint8 ``[env.num_envs, ρ, ρ, ρ]``, from ``control.bodies`` (``ControlRunConfig``);
    given fewer bodies than environments, each is repeated in turn."""
    from freeform.body import check_grids
    from freeform.records import read_record

    control, n = cfg.control, cfg.env.num_envs
    assert control is not None
    source = control.bodies

    sizes = (cfg.env.resolution, cfg.task.materials, cfg.env.steps, cfg.env.bundle_size)
    if source == "walker":
        from freeform.envs.untrained import DesignBodies, untrained_walker

        grids, _ = untrained_walker(control.candidates, DesignBodies(*sizes), control.body_seed, sim=cfg.sim,
                                    control=control.episode(), arch=arch)
    elif source == "untrained_designs":  # (the rare empty body is dropped, and the others repeat in its place)
        from freeform.envs.untrained import untrained_design_bodies

        grids = untrained_design_bodies(max(n, control.teachers + control.teachers // 8 + 1), *sizes,
                                        control.body_seed)
        grids = grids[(grids.flatten(1) > 0).any(dim=1)]
    else:
        from pathlib import Path

        path = Path(source)
        if not path.is_file():
            from freeform.config import BODY_SOURCES

            raise ValueError(f"control.bodies must be one of {list(BODY_SOURCES)} or a file of bodies (a .npy of grids "
                             f"or a design record .npz), and there is no file {source!r}")
        if path.suffix == ".npz":
            record = read_record(path)
            best = np.argsort(-record.rewards, kind="stable")[: control.top]
            grids = torch.from_numpy(record.placed_grids()[best])
        elif path.suffix == ".npy":
            grids = torch.from_numpy(np.load(path, allow_pickle=False))
            grids = grids[None] if grids.dim() == 3 else grids
        else:
            raise ValueError(f"control.bodies: {source!r} is neither a .npy of grids nor a design record .npz")
        if grids.dtype != torch.uint8 or grids.dim() != 4:
            raise ValueError(f"control.bodies: {source!r} must hold uint8 grids [ρ, ρ, ρ] or [M, ρ, ρ, ρ], got "
                             f"{grids.dtype} {list(grids.shape)}")
        check_grids(grids, len(cfg.sim.materials) + 1, name=f"control.bodies ({source})")
        empty = (~(grids.flatten(1) > 0).any(dim=1)).nonzero().flatten().tolist()
        if empty:
            raise ValueError(f"control.bodies: {source!r} has empty grids (no voxel) at {empty[:5]}")
    if control.teachers:  # (one teacher per body: the first M, environment i driving body i mod M)
        if len(grids) < control.teachers:
            raise ValueError(f"control.teachers={control.teachers}: control.bodies={source!r} gives only "
                             f"{len(grids)} bodies")
        grids = grids[: control.teachers]
    return grids[torch.arange(n) % len(grids)].contiguous()


def control_env(cfg: TrainConfig, device: torch.device, envs: tuple[int, int], seed: int,
                bodies: torch.Tensor | None = None, box: tuple[int, int, int] | None = None,
                shared_headings: bool = True) -> Any:
    """The run's ``ControlEnv`` of environments ``envs = (lo, hi)``, seeded ``seed``: their bodies are ``bodies``
    (``[hi − lo, ρ, ρ, ρ]``; default: :func:`control_bodies`' ``lo … hi−1``), padded to ``box`` if given (the box a
    controller was built for). With ``control.bodies=codesign`` a ``CodesignEnv`` (its bodies are designed).
    ``shared_headings``: a bank's copies of a body walk one heading (training); False: each environment its own
    draw (an evaluation's episodes, which a baseline does not compare)."""
    from freeform.envs.control import ControlEnv

    assert cfg.control is not None
    arch = "cuda" if device.type == "cuda" else "cpu"
    if cfg.control.codesign:  # each episode designs its bodies
        from freeform.envs.codesign import CodesignEnv

        return CodesignEnv(envs[1] - envs[0], cfg.env, cfg.task.materials, cfg.sim, cfg.control.episode(), seed=seed,
                           device=device, first_env=envs[0])
    if cfg.control.bodies == "population" and bodies is None:  # fresh bodies every few episodes
        from freeform.envs.population import DesignBodies, PopulationControlEnv, Stream
        from freeform.run.designer import TrainedDesigner

        e, c = cfg.env, cfg.control
        designer = TrainedDesigner(c.designer) if c.designer is not None else None
        sizes = DesignBodies(e.resolution, cfg.task.materials, e.steps, e.bundle_size, designer)
        stream = Stream(e.num_envs, pool=c.pool, refresh_every=c.refresh_every, body_seed=c.body_seed,
                        copies=c.copies, box=box)
        return PopulationControlEnv(sizes, stream, sim=cfg.sim, control=c.episode(), seed=seed, device=device,
                                    envs=envs)
    bodies = control_bodies(cfg, arch)[envs[0]:envs[1]] if bodies is None else bodies
    if box is None and cfg.algo.name == "distill" and cfg.algo.symmetry == "ground":
        from freeform.agents.controller_file import body_box

        need = body_box(bodies)  # (a square footprint: the quarter turns and the diagonal mirrors map it onto itself)
        box = (max(need[:2]), max(need[:2]), need[2])
    # a bank's copies of a body share its heading (as a population env's do): its leave-one-out baseline and its
    # per-body advantages then compare the noise's effects, not the luck of a copy's heading against its siblings'
    body = torch.arange(envs[0], envs[1]) % cfg.control.teachers if cfg.control.teachers else None
    env = ControlEnv(bodies, sim=cfg.sim, control=cfg.control.episode(), seed=seed, device=device,
                     first_env=body.numpy() if body is not None and shared_headings else envs[0], box=box)
    if body is not None:  # (each environment's observation names its body's teacher)
        from freeform.agents.distill.teachers import TeacherIndex

        env = TeacherIndex(env, body)
    return env


def build(cfg: TrainConfig, device: torch.device, envs: tuple[int, int] | None = None) -> tuple[VecEnv, Learner]:
    """The run's env — the design env (the one scoring with the task; a learner may wrap it), or in a control run
    (``cfg.control``) the control env — and learner, seeded by ``cfg.seed`` (the same cfg builds the same objects).

    ``envs = (lo, hi)``: build only environments ``lo … hi−1`` of ``env.num_envs`` (this rank's slice in a
    data-parallel run, :func:`freeform.agents.distributed.env_slice`); default all of them.
    """
    if cfg.algo.name not in LEARNERS:
        raise ValueError(f"algo.name must be one of {sorted(LEARNERS)}, got {cfg.algo.name!r}")
    seed_everything(cfg.seed)
    envs = envs if envs is not None else (0, cfg.env.num_envs)
    if cfg.control is not None:
        env = control_env(cfg, device, envs, cfg.seed)
    else:
        env = design_env(cfg, device, envs[1] - envs[0], cfg.seed)
    learner = LEARNERS[cfg.algo.name](cfg, env, device, envs)
    if not isinstance(learner, Learner):
        raise ValueError(f"algo.name={cfg.algo.name!r} built a {type(learner).__name__}, which is no freeform.learner.Learner")
    return env, learner


def read_saved_controller(source: str, field: str, box: tuple[int, int, int] | None = None) -> torch.nn.Module:
    """The controller that config field ``field`` names (``source``: a ``controller.pt``, a results folder holding
    one, a control run's directory or checkpoint; ``freeform.agents.controller_file.read_controller``), built for
    ``box`` if given; a missing or unreadable source is refused naming the field."""
    return _read_saved(source, field, box).controller


def controller_source(source: str) -> Path:
    """The file a config's controller field names: a zoo name (``freeform.zoo.resolve``), a path, or a path of a run
    made before the lab moved out of docs/ (``docs/results/...``, which its saved config names) read where it is now
    (``lab/results/...``), with a warning. Refused, naming the zoo, where it is none of these."""
    from freeform.zoo import resolve

    if source.startswith("docs/results/") and not Path(source).exists():
        now = "lab/results/" + source[len("docs/results/"):]
        if Path(now).exists():
            logging.getLogger(__name__).warning("%s moved to %s (the lab's results left docs/): reading it there",
                                                source, now)
            source = now
    return resolve(source)


def _read_saved(source: str, field: str, box: tuple[int, int, int] | None = None) -> Any:
    """:func:`read_saved_controller`'s ``SavedController`` (the network with its ``ControlConfig``)."""
    from freeform.agents.controller_file import read_controller

    try:  # (a source that is neither a zoo name nor a file is refused, naming the zoo)
        return read_controller(controller_source(source), box=box)
    except ValueError as e:
        raise ValueError(f"{field}={source!r}: {e}") from e


def load_controller(controller: torch.nn.Module, source: str, frame: str = "world") -> None:
    """``control.controller_init``: a trained controller's weights into ``controller`` — from a ``controller.pt``, a
    results folder holding one, a control run's policy or a co-design run's controller part (a run's directory or
    checkpoint file: ``freeform.agents.controller_file.read_controller``). A kind that grows from another
    (``grows_from``: ``attention_gru``'s memory, ``attention_hyper``'s generator) also starts from that kind's
    weights, what it adds silent until trained."""
    from freeform.agents.networks.controllers import controller_kind

    saved = _read_saved(source, "control.controller_init")
    trained = saved.controller
    if saved.control.frame != frame:  # (a start, not an error: weights of either frame; the steering teachers')
        logging.getLogger(__name__).warning(
            "control.controller_init=%r was trained on observations in the %s frame and this run's are in the %s "
            "frame (control.frame): its weights start reading turned vectors", source, saved.control.frame, frame)
    ours, theirs = getattr(controller, "wave", None), getattr(trained, "wave", None)
    wave = ("k", "amplitude", "gain")
    if ours is not None and theirs is not None and [ours[k] for k in wave] != [theirs[k] for k in wave]:
        # (the hand-set wave and its gain are no weights: loaded under others, the heads would play another gait)
        raise ValueError(f"control.controller_init={source!r} plays the hand-set wave k = {theirs['k']}, amplitude "
                         f"{theirs['amplitude']} at gain {theirs['gain']}; this run's is k = {ours['k']}, amplitude "
                         f"{ours['amplitude']}, gain {ours['gain']}: set control.wave_k, control.wave_amplitude and "
                         "control.wave_gain to the file's")
    # (a kind may start from the one it grows from: everything but what it adds, which starts silent)
    grows = getattr(controller, "grows_from", None) == controller_kind(trained)
    try:
        loaded = controller.load_state_dict(trained.state_dict(), strict=not grows)
        detail = ""
    except RuntimeError as e:
        detail = "; ".join(line.strip() for line in str(e).splitlines()[:3])
    if grows and not detail:
        missing = [k for k in loaded.missing_keys if not k.startswith(controller.grown_prefixes)]
        detail = f"missing {missing}, unexpected {loaded.unexpected_keys}" if missing or loaded.unexpected_keys else ""
    if detail:
        raise ValueError(f"control.controller_init={source!r} holds another controller than this run builds (kind "
                         f"or width: control.controller, control.hidden): {detail}")


@register_learner("ppo")
def _ppo(cfg: TrainConfig, env: Any, device: torch.device, envs: tuple[int, int]) -> Learner:
    """PPO with the paper's actor-critic (a control run: ``control.controller``); ``env.dense_every`` wraps the env
    in dense rewards, ``agent.eval_every`` adds a deterministic evaluation env of its own (seed + 1)."""
    from freeform.agents import PPO, CodesignActorCritic, VoxelActorCritic, build_controller
    from freeform.agents.networks import resolve_trunk

    # The design trunk's fastest form inside a CUDA graph differs from the eager one (resolve_trunk): chosen here,
    # where it is known; an eager run keeps "auto", resolved by the network per device.
    trunk = resolve_trunk(cfg.agent.trunk, device, graphed=True) if cfg.agent.cuda_graph else cfg.agent.trunk
    if cfg.control is not None:
        control = cfg.control
        width = control.hidden if control.hidden is not None else cfg.agent.hidden
        if control.codesign:
            policy = CodesignActorCritic.for_env(env, hidden=cfg.agent.hidden, controller_hidden=width,
                                                 log_std=control.init_log_std, controller=control.controller,
                                                 head=control.head, wave=control.hand_set_wave, trunk=trunk)
        else:  # (freeform.agents.networks.controllers.CONTROLLERS; a bank's teachers are built for the env it wraps)
            policy = build_controller(control.controller, env.env if control.teachers else env, width,
                                      control.init_log_std, control.head, control.hand_set_wave)
        if control.controller_init is not None:
            load_controller(policy.controller if (control.codesign or control.privileged_critic) else policy,
                            control.controller_init, control.frame)
        if control.teachers:
            from freeform.agents.distill.teachers import TeacherBank

            policy = TeacherBank.from_template(policy, control.teachers)
        # (a control run's evaluation: this rank's bodies again, not searched again)
        own = control.codesign or control.bodies == "population"  # (bodies of its own: designed, or a stream)
        eval_env = control_env(cfg, device, envs, cfg.seed + 1, bodies=None if own else env.grids,
                               shared_headings=False) if (
            cfg.agent.eval_every) else None
        if control.prior is not None:
            env = _with_prior(env, control.prior, control.prior_coeff, device)
        return PPO(env, policy, ppo_config(cfg, device=str(device)), eval_env=eval_env)

    if cfg.env.dense_every:  # the partial body scored every k steps; records and returns keep the terminal reward
        from freeform.envs import DenseDesignReward

        env = DenseDesignReward(env, cfg.env.dense_every)
    policy = VoxelActorCritic(resolution=cfg.env.resolution, materials=cfg.task.materials, hidden=cfg.agent.hidden,
                              trunk=trunk)
    eval_env = design_env(cfg, device, envs[1] - envs[0], cfg.seed + 1) if cfg.agent.eval_every else None
    return PPO(env, policy, ppo_config(cfg, device=str(device)), eval_env=eval_env)


def _with_prior(env: Any, source: str, coeff: float, device: torch.device) -> Any:
    """``env`` whose reward gains ``control.prior``'s log-likelihood (``freeform.agents.distill.prior.PriorReward``)."""
    from freeform.agents.distill.prior import PriorReward

    prior = read_saved_controller(source, "control.prior", box=tuple(env.box))
    shape = env.observation_shape
    channels = (shape["policy"] if isinstance(shape, dict) else shape)[0]
    if prior.init_kwargs.get("channels") != channels:
        raise ValueError(f"control.prior={source!r} reads {prior.init_kwargs.get('channels')} observation channels "
                         f"and this run's env gives {channels} (control.residual, control.response: the prior's)")
    return PriorReward(env, prior.to(device), coeff)


@register_learner("distill")
def _distill(cfg: TrainConfig, env: Any, device: torch.device, envs: tuple[int, int]) -> Learner:
    """DAgger from the teacher run ``algo.teacher`` (a bank of per-body controllers on this run's bodies) into the
    controller ``control.controller`` / ``control.head`` (``freeform.agents.distill``)."""
    from freeform.agents import build_controller
    from freeform.agents.distill import BankTeacher, Distillation, DistillConfig
    from freeform.agents.networks.group_average import check_turnable

    control = cfg.control
    assert control is not None and control.teachers
    if is_selection(Path(str(cfg.algo.teacher))):
        teacher, kinds = chosen_teacher(cfg, device, env)
    else:
        bank = teacher_bank(cfg, device, env.env.grids, env.teacher)
        teacher, kinds = BankTeacher(bank, env.teacher), {"the teacher run's controller": bank.init_kwargs["kind"]}
    width = control.hidden if control.hidden is not None else cfg.agent.hidden
    student = build_controller(control.controller, env.env, width, control.init_log_std, control.head,
                               control.hand_set_wave)
    if control.controller_init is not None:
        load_controller(student, control.controller_init, control.frame)
    if cfg.algo.symmetry != "none":
        check_turnable("algo.symmetry", cfg.algo.symmetry, control.headings, control.frame,
                       {"control.controller": control.controller, **kinds})
    return Distillation(env.env, student, teacher, ppo_config(cfg, device=str(device)),
                        DistillConfig.from_algo(cfg.algo), first_env=envs[0], total_envs=cfg.env.num_envs)


def teacher_bank(cfg: TrainConfig, device: torch.device, grids: torch.Tensor, body: torch.Tensor) -> Any:
    """``algo.teacher``'s bank of per-body controllers, checked against this run: the same number of teachers and
    episode settings (each field that differs named), and the same bodies — ``grids``, this run's environments',
    each the teacher run's body ``body`` (``TeacherIndex.teacher``), grid for grid."""
    source = Path(str(cfg.algo.teacher))
    run = read_teacher_run(source, f"algo.teacher={source}", "cuda" if device.type == "cuda" else "cpu")
    theirs, mine = run.config.control, cfg.control
    assert theirs is not None and mine is not None
    keys = ("teachers", "bodies", "body_seed", "top", *vars(mine.episode()))
    differ = described_differences(theirs, mine, "the teacher run", keys,
                                   bank=True)  # (a student may sense more: its response channels)
    if differ:
        raise ValueError(f"algo.teacher={source}: its teachers were trained with other settings than this run's: "
                         + "; ".join(differ) + " (give this run the teacher run's values, or train teachers with these)")
    _same_physics(run.config.sim, cfg.sim, mine.episode(), f"algo.teacher={source}: its teachers were trained",
                  "the teacher run", "train teachers under this run's")
    _same_bodies(run.bodies, grids.cpu(), body.cpu(), run.config, cfg, source)
    return run.bank.to(device)


def _same_physics(theirs: SimConfig, mine: SimConfig, episode: ControlConfig, who: str, whose: str,
                  remedy: str) -> None:
    """Refuses teachers that moved in another simulator than this run's (``ControlEnv.physics_differences``)."""
    from freeform.envs.control import ControlEnv

    if other := ControlEnv.physics_differences(theirs, mine, episode, whose):
        raise ValueError(f"{who} in another simulator than this run's: {other} (give this run {whose}'s sim values, "
                         f"or {remedy})")


def is_selection(source: Path) -> bool:
    """Whether ``algo.teacher`` names an ``lab.selection --try`` folder (each body's controller chosen by
    trial) rather than a teacher run."""
    return (source / "run.json").is_file() and "tried" in json.loads((source / "run.json").read_text())


def chosen_teacher(cfg: TrainConfig, device: torch.device, env: Any) -> tuple[Any, dict[str, str]]:
    """``algo.teacher``'s selection (:func:`is_selection`) as a teacher: body m taught by the controller chosen for
    it. Checked against this run: the same bodies (its ``--bodies`` file, read as it read them, grid for grid with
    this run's), episode and simulator (every field that differs named); recurrent controllers refused (a teacher
    here labels each observation alone). Returns (the teacher, each tried controller's kind by its file)."""
    from freeform.agents.distill import ChosenTeacher
    from freeform.agents.networks.recurrent import RecurrentPolicy
    from freeform.body import largest_component
    from freeform.envs.control import ControlConfig
    from freeform.sim import SimConfig

    source = Path(str(cfg.algo.teacher))
    run = json.loads((source / "run.json").read_text())
    with open(source / "bodies.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    name = f"algo.teacher={source}"
    if not Path(run["bodies"]).is_file():
        raise ValueError(f"{name}: its bodies file {run['bodies']} is not there (run from where it was tried)")
    grids = np.load(run["bodies"], allow_pickle=False)
    theirs = largest_component(torch.from_numpy((grids[None] if grids.ndim == 3 else grids).astype(np.uint8)))
    mine = largest_component(env.env.grids.cpu())
    if len(theirs) != cfg.control.teachers or theirs.shape[1:] != mine.shape[1:] or \
            not torch.equal(theirs[env.teacher.cpu()], mine):
        raise ValueError(f"{name}: its {len(theirs)} bodies ({run['bodies']}) are not this run's "
                         f"{cfg.control.teachers} (control.teachers, control.bodies={cfg.control.bodies!r}): give "
                         "control.bodies its --bodies file and control.teachers its body count")
    episode = ControlConfig(**{**vars(cfg.control.episode()), **{k: v for k, v in run["control"].items()
                                                                if k in vars(cfg.control.episode())}})
    differ = described_differences(episode, cfg.control.episode(), "the selection", tuple(vars(episode)))
    if differ:
        raise ValueError(f"{name}: its controllers were tried in another episode than this run's: " + "; ".join(differ))
    saved = [_read_saved(str(p), "algo.teacher", box=tuple(env.env.box)) for p in run["tried"]]
    # (the selection played every controller in the first one's simulator)
    _same_physics(saved[0].sim or SimConfig(), cfg.sim, episode, f"{name}: its controllers were tried",
                  "the selection", "re-make the selection with --try under this run's")
    nets = [s.controller.to(device) for s in saved]
    recurrent = [p for p, n in zip(run["tried"], nets, strict=True) if isinstance(n, RecurrentPolicy)]
    if recurrent:
        raise ValueError(f"{name}: {recurrent[0]} is recurrent; a chosen teacher labels each observation alone "
                         "(select among feed-forward controllers)")
    unknown = sorted({r["chosen"] for r in rows} - set(run["names"]))
    if len(rows) != len(theirs) or unknown:
        raise ValueError(f"{name}: its bodies.csv has {len(rows)} rows for {len(theirs)} bodies"
                         f"{f', and chooses {unknown} among none tried' if unknown else ''} (re-make it with --try)")
    choice = torch.tensor([run["names"].index(r["chosen"]) for r in rows])
    return ChosenTeacher(nets, choice, env.teacher), {str(p): s.kind for p, s in zip(run["tried"], saved, strict=True)}


class TeacherRun(NamedTuple):
    """A teacher run read back: its checkpoint's payload, its config, its bank (weights loaded), its M bodies."""

    payload: dict[str, Any]
    config: TrainConfig
    bank: Any
    bodies: torch.Tensor


def read_teacher_run(source: Path, name: str, arch: str = "cpu") -> TeacherRun:
    """A teacher run (``source``: its directory or a checkpoint): its bank and its bodies (:func:`teacher_bodies`);
    ``name`` says who asked, in the refusals."""
    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint, resolve_checkpoint
    from freeform.config import from_container

    path = resolve_checkpoint(source)
    if not path.is_file():
        raise ValueError(f"{name}: no teacher run or checkpoint there ({path} is not a file; a run of "
                         "experiment=control_teachers_cpu writes one)")
    payload = load_checkpoint(path)
    bank = bank_from_checkpoint(payload, str(source))
    config = from_container(payload["config"])
    return TeacherRun(payload, config, bank, teacher_bodies(path, config, bank.teachers, arch, payload.get("bodies")))


def teacher_bodies(source: Path, cfg: TrainConfig, teachers: int, arch: str = "cpu",
                   stored: torch.Tensor | None = None) -> torch.Tensor:
    """A teacher run's M bodies, uint8 ``[M, ρ, ρ, ρ]`` (``source``: its directory or a checkpoint in it; ``cfg``
    its config): those its checkpoint holds (``stored``: a pooled run's, ``freeform.run.teacher_runs``), else its
    records' (what it trained on), else what its config gives — the same ``control.bodies`` can name other grids
    elsewhere (the untrained designs depend on ``env.num_envs``; a file may change)."""
    from freeform.checkpoint import run_dir_of
    from freeform.records import read_record

    if stored is not None:
        return stored[:teachers]
    records = sorted((run_dir_of(source) / "records").glob("epoch_*.npz"))
    if records:
        return torch.from_numpy(read_record(records[0]).final_grids[:teachers])
    return control_bodies(cfg, arch)[:teachers]


def _same_bodies(their_bodies: torch.Tensor, my_grids: torch.Tensor, body: torch.Tensor, theirs: TrainConfig,
                 mine: TrainConfig, source: Path) -> None:
    """This run's environments' grids ``my_grids`` are the teacher run's bodies ``their_bodies[body]``, grid for
    grid (refused naming the bodies that differ and what to do)."""
    from freeform.checkpoint import run_dir_of

    if their_bodies.shape[1:] != my_grids.shape[1:]:
        raise ValueError(f"algo.teacher={run_dir_of(source)}: its bodies are grids {list(their_bodies.shape[1:])}, "
                         f"this run's {list(my_grids.shape[1:])} (env.resolution {theirs.env.resolution} there, "
                         f"{mine.env.resolution} here): train teachers on these bodies")
    rows = (their_bodies[body] != my_grids).flatten(1).any(1)
    differ = sorted(set(body[rows].tolist()))
    if differ:
        assert mine.control is not None
        raise ValueError(f"algo.teacher={run_dir_of(source)}: its bodies are not this run's (bodies {differ[:5]} differ; "
                         f"control.bodies={mine.control.bodies!r} gives other grids here — the untrained designs "
                         f"depend on env.num_envs, {theirs.env.num_envs} there and {mine.env.num_envs} here — or "
                         "its file changed): give this run the teacher run's env.num_envs, or train teachers on these")


@register_learner("ga", "cmaes", "grid_ga")
def _evolution(cfg: TrainConfig, env: Any, device: torch.device, envs: tuple[int, int]) -> Learner:
    """An evolutionary optimiser over the same env, task and simulator; one process."""
    from freeform.evolve import build_evolution

    if envs != (0, cfg.env.num_envs):
        raise ValueError(f"algo.name={cfg.algo.name} runs in one process; launch it without torchrun")
    return build_evolution(cfg.algo, env, cfg.seed)


__all__ = ["LEARNERS", "TASKS", "build", "build_task", "control_bodies", "control_env", "design_env", "register_learner", "register_task",
           "resolve_device", "seed_everything", "task_builders"]
