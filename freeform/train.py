"""The training application: ``freeform-train`` / ``python -m freeform.train`` (a Hydra app over ``conf/``).

    freeform-train                                   # the CPU demo (experiment=volume_cpu)
    freeform-train experiment=paper_volume           # paper Table I, volume
    freeform-train -m experiment=paper_volume seed=0,1,2,3,4   # five trials, one directory each
    freeform-train trainer.resume=runs/volume_cpu/2026-01-01_12-00-00 trainer.epochs=80
    freeform-train hydra.run.dir=runs/mine      # again after a kill or SIGTERM: continues (trainer.resume=auto)
    torchrun --nproc_per_node=4 -m freeform.train experiment=paper_locomotion   # one run on 4 GPUs (docs/scaling.md)
    freeform-train trainer.dry_run=true ...          # print the per-rank split and the launch command, run nothing
    freeform-train algo=ga                           # an evolutionary baseline instead of PPO (algo=cmaes, grid_ga)

Each epoch: PPO collects one rollout and updates (``PPO.train_epoch``) — or, with ``algo=ga|cmaes|grid_ga``, an
evolutionary optimiser scores and breeds one generation (``freeform.evolve.Evolution.train_epoch``); the trainer
then cuts the rollout into finished episodes, writes the epoch's design record, logs scalars to TensorBoard, runs
the per-epoch callbacks (renders), flushes, and only then checkpoints — so whatever a checkpoint claims is already
on disk, and a run killed at any moment resumes from its last checkpoint with no gap. The run directory's layout is
in ``docs/training.md``.

On SIGTERM/SIGUSR2 (a cluster's preemption or time limit) the run finishes the epoch in progress, checkpoints and
exits with status 75, "requeue me" (``freeform.preemption``); with ``trainer.resume=auto`` (the default) the same
command in the same run directory continues it. A failed write (disk full, quota, a vanished mount) stops the run
cleanly with a one-line reason and status 1, the previous ``last.pt`` intact.

Python use: ``train(cfg, run_dir)`` with a :class:`freeform.config.TrainConfig`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import random
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

import freeform
from freeform import preemption
from freeform._conf_dir import conf_dir
from freeform.agents import distributed
from freeform.checkpoint import (
    AUTO,
    CHECKPOINT_DIR,
    LAST,
    CheckpointError,
    CheckpointWriteError,
    auto_checkpoint,
    capture_rng_state,
    load_checkpoint,
    numbered_name,
    resolve_checkpoint,
    restore_rng_state,
    run_dir_of,
    save_checkpoint,
)
from freeform.config import (
    TrainConfig,
    flatten,
    from_container,
    ppo_config,
    register_configs,
    to_container,
    to_dataclass,
    validate,
)
from freeform.envs.base import ReportsStats, Task, VecEnv
from freeform.files import write_atomically
from freeform.logger import Logger
from freeform.records import EpisodeCollector, EpochRecord, record_path, write_record
from freeform.sim import runtime as sim_runtime

log = logging.getLogger("freeform.train")

CONF_DIR = conf_dir()  # the installed package data or the checkout's conf/ (freeform/_conf_dir.py)
RUN_INFO = "run_info.json"

# ------------------------------------------------------------------------------------------------ task registry

TaskBuilder = Callable[[TrainConfig, torch.device], Task]
TASKS: dict[str, TaskBuilder] = {}
"""``task.name`` -> builder ``(cfg, device) -> Task``. Add one with :func:`register_task`."""


def register_task(name: str) -> Callable[[TaskBuilder], TaskBuilder]:
    """Decorator: make ``task.name=<name>`` build its task with the decorated function."""

    def decorate(builder: TaskBuilder) -> TaskBuilder:
        TASKS[name] = builder
        return builder

    return decorate


@register_task("volume")
def _volume_task(cfg: TrainConfig, device: torch.device) -> Task:
    from freeform.envs import VolumeTask

    return VolumeTask(**cfg.task.options)


def _simulator_options(cfg: TrainConfig, device: torch.device) -> dict[str, Any]:
    """A simulated task's constructor arguments: the run's ``sim`` and device, and the simulator's arch taken from
    the run's device (no silent CPU fallback under a GPU run: resolve_device checked CUDA); ``task.options`` win."""
    return {"sim": cfg.sim, "device": device, "arch": "cuda" if device.type == "cuda" else "cpu", **cfg.task.options}


@register_task("locomotion")
def _locomotion_task(cfg: TrainConfig, device: torch.device) -> Task:
    from freeform.envs import LocomotionTask

    return LocomotionTask(**_simulator_options(cfg, device))


def _trajectory_task(cfg: TrainConfig, device: torch.device) -> Task:
    """A ``TrajectoryTask`` of the reward registered as ``task.name`` (freeform/envs/trajectory.py)."""
    from freeform.envs import TrajectoryTask

    return TrajectoryTask(cfg.task.name, **_simulator_options(cfg, device))


def build_task(cfg: TrainConfig, device: torch.device) -> Task:
    """The run's task from the registry, checked against the :class:`freeform.envs.Task` protocol."""
    from freeform.envs.trajectory import TRAJECTORY_REWARDS

    # Every reward registered with trajectory_reward (the built-ins and a user's own) is a task of that name.
    builders = {**dict.fromkeys(TRAJECTORY_REWARDS, _trajectory_task), **TASKS}
    if cfg.task.name not in builders:
        raise ValueError(f"task.name must be one of {sorted(builders)}, got {cfg.task.name!r}")
    task = builders[cfg.task.name](cfg, device)
    if not isinstance(task, Task):
        raise ValueError(f"task.name={cfg.task.name!r} built a {type(task).__name__}, which has no reward(final_grids)")
    return task


# ------------------------------------------------------------------------------------------------ building a run


def resolve_device(name: str, experiment: str | None = None) -> torch.device:
    """``trainer.device`` -> a torch device (``auto``: CUDA when available, else CPU; ``cuda``: this process's
    current GPU, which is the rank's own under torchrun, see ``distributed.pin_local_gpu``).

    A run that asks for CUDA where there is none stops here with one line naming the override that runs it on the
    CPU anyway (the paper's GPU presets set ``trainer.device: cuda``)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        what = f"experiment={experiment} is meant for a GPU (trainer.device={name})" if experiment else f"trainer.device={name}"
        raise ValueError(f"{what} but no CUDA device is available here; add trainer.device=cpu to run it on the CPU anyway")
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return device


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch's global RNGs (the network's initialisation draws from torch's)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def build(
    cfg: TrainConfig, device: torch.device, envs: tuple[int, int] | None = None
) -> tuple[VecEnv, torch.nn.Module, Any]:
    """The run's environment, policy and PPO, seeded by ``cfg.seed`` (the same cfg builds the same objects).

    With ``algo.name`` other than ``ppo`` the third object is the evolutionary optimiser (``freeform.evolve``,
    PPO's ``train_epoch()/state_dict()/checkpoint()`` surface) on the same environment, and there is no policy.

    ``envs = (lo, hi)``: build only environments ``lo … hi−1`` of ``env.num_envs`` (this rank's slice in a
    data-parallel run, :func:`freeform.agents.distributed.env_slice`); default all of them.
    """
    from freeform.agents import PPO, VoxelActorCritic
    from freeform.envs import DesignEnv

    seed_everything(cfg.seed)
    lo, hi = envs if envs is not None else (0, cfg.env.num_envs)
    env = DesignEnv(
        num_envs=hi - lo,
        resolution=cfg.env.resolution,
        materials=cfg.task.materials,
        steps=cfg.env.steps,
        bundle_size=cfg.env.bundle_size,
        task=build_task(cfg, device),
        device=device,
        seed=cfg.seed,
        action_bound=cfg.env.action_bound,
        mirror_y=cfg.env.mirror_y,
    )
    if cfg.algo.name != "ppo":  # evolution: the same env, task and simulator; one process
        from freeform.evolve import build_evolution

        if (lo, hi) != (0, cfg.env.num_envs):
            raise ValueError(f"algo.name={cfg.algo.name} runs in one process; launch it without torchrun")
        return env, None, build_evolution(cfg.algo, env, cfg.seed)
    if cfg.env.dense_every:  # the partial body scored every k steps; records and returns keep the terminal reward
        from freeform.envs import DenseDesignReward

        env = DenseDesignReward(env, cfg.env.dense_every)
    policy = VoxelActorCritic(resolution=cfg.env.resolution, materials=cfg.task.materials, hidden=cfg.agent.hidden)
    eval_env = None
    if cfg.agent.eval_every:  # deterministic evaluation episodes on an env of their own (charts/eval_return)
        eval_env = DesignEnv(num_envs=hi - lo, resolution=cfg.env.resolution, materials=cfg.task.materials,
                             steps=cfg.env.steps, bundle_size=cfg.env.bundle_size, task=build_task(cfg, device), device=device,
                             seed=cfg.seed + 1, action_bound=cfg.env.action_bound,
                             mirror_y=cfg.env.mirror_y)
    ppo = PPO(env, policy, ppo_config(cfg, device=str(device)), eval_env=eval_env)
    return env, policy, ppo


# ------------------------------------------------------------------------------------------------ callbacks


@dataclass
class EpochContext:
    """What a per-epoch callback sees, after the epoch's scalars are written and before its checkpoint.

    ``epoch``: 0-based index of the epoch just trained; ``global_step``: environment steps so far (the TensorBoard
    step); ``episodes``: the epoch's finished episodes as written to its design record (``final_grids [E, ρ, ρ, ρ]
    uint8``, ``rewards [E]``, ``actions [E, T, A]``, ``values [E, T]``, ``metrics`` {name: [E]}) or None;
    ``ppo.episode_infos`` holds the environment's own info dicts (``bodies`` ...).
    """

    epoch: int
    global_step: int
    stats: dict[str, float]
    episodes: dict[str, Any] | None
    cfg: TrainConfig
    run_dir: Path
    logger: Logger
    ppo: Any


EpochCallback = Callable[[EpochContext], None]


def render_callback(every: int) -> EpochCallback:
    """At epochs 0, ``every``, 2·``every``, ... log renders of the epoch's bodies to TensorBoard
    (``freeform.render.log_bodies(writer, final_grids, rewards, step, cfg)``: best, median and a random body)."""

    def callback(ctx: EpochContext) -> None:
        if ctx.episodes is None or ctx.epoch % every:  # epochs 0, every, 2·every, ...
            return
        try:
            from freeform.render import log_bodies
        except ImportError as exc:
            raise ValueError("trainer.render_every > 0 needs freeform.render.log_bodies, not available") from exc
        log_bodies(ctx.logger.writer, ctx.episodes["final_grids"], ctx.episodes["rewards"], ctx.global_step, ctx.cfg)

    return callback


def default_callbacks(cfg: TrainConfig) -> list[EpochCallback]:
    """The callbacks a run gets from its config (``trainer.render_every``)."""
    return [render_callback(cfg.trainer.render_every)] if cfg.trainer.render_every else []


# ------------------------------------------------------------------------------------------------ run metadata


def _git_commit(package: Path | None = None) -> tuple[str | None, bool | None]:
    """The commit (and whether the work tree differs from it) of the freeform checkout that ``package`` (the
    imported ``freeform`` directory) lies in; ``(None, None)`` when it is not a checkout's own tracked source — a
    wheel installed inside another repository (a venv in a user's project) would otherwise report that project's
    commit. ``run_info.json`` then has the installed version alone (``freeform``)."""
    package = (package or Path(freeform.__file__).resolve().parent).resolve()
    repo = package.parent

    def git(*args: str) -> subprocess.CompletedProcess[str] | None:
        try:
            return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None

    top = git("rev-parse", "--show-toplevel")
    if top is None or top.returncode or Path(top.stdout.strip()).resolve() != repo:
        return None, None
    tracked = git("ls-files", "--error-unmatch", str(package / "__init__.py"))
    sha = git("rev-parse", "HEAD")
    if tracked is None or tracked.returncode or sha is None or sha.returncode:
        return None, None
    dirty = git("status", "--porcelain", "--untracked-files=no")
    return sha.stdout.strip(), bool(dirty.stdout.strip()) if dirty is not None and dirty.returncode == 0 else None


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def run_info(cfg: TrainConfig, device: torch.device) -> dict[str, Any]:
    """What made this run: versions, device, git commit, start time (``run_info.json``)."""
    commit, dirty = _git_commit()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else (platform.processor() or platform.machine())
    return {
        "device": str(device),
        "device_name": name,
        "freeform": freeform.__version__,
        "torch": torch.__version__,
        "taichi": _version("taichi"),
        "sim_backend": sim_runtime.describe(cfg.sim.backend),  # "taichi 1.7.4" | "quadrants 1.3.3": what ran the kernels
        "numpy": np.__version__,
        "python": platform.python_version(),
        "git_commit": commit,
        "git_dirty": dirty,
        "start_time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "hostname": socket.gethostname(),
        "command": sys.argv,
        "experiment": cfg.name,
        "seed": cfg.seed,
        "world_size": distributed.world_size(),
        "resumes": [],
    }


def _write_json(path: Path, data: dict[str, Any]) -> None:
    text = json.dumps(data, indent=2, default=str) + "\n"
    write_atomically(path, lambda f: f.write(text.encode()))


# ------------------------------------------------------------------------------------------------ resuming


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("~+")


def resume_config(saved: TrainConfig, current: TrainConfig, overrides: Sequence[str] | None) -> TrainConfig:
    """The config of a resumed run: the checkpoint's own, with the ``trainer`` fields given on the command line.

    ``overrides`` (Hydra's command-line overrides) name what the user set; ``None`` (Python use) takes the whole
    ``trainer`` section of ``current``. Any other explicitly set key must equal the checkpoint's value: changing
    what the run trains mid-way would break the promise that a resumed run equals an uninterrupted one.
    """
    trainer = dataclasses.replace(saved.trainer, resume=current.trainer.resume)
    if overrides is None:
        trainer = dataclasses.replace(current.trainer)
    else:
        saved_flat, current_flat = flatten(to_container(saved)), flatten(to_container(current))
        for override in overrides:
            key = _override_key(override)
            if key.startswith("hydra.") or key == "trainer.resume":
                continue
            if key.startswith("trainer."):
                field = key.split(".", 1)[1]
                trainer = dataclasses.replace(trainer, **{field: getattr(current.trainer, field)})
            elif key == "experiment":
                if current.name != saved.name:
                    raise ValueError(f"experiment: the run being resumed is {saved.name!r}, not {current.name!r}")
            else:
                changed = [k for k in current_flat if (k == key or k.startswith(key + ".")) and current_flat[k] != saved_flat.get(k)]
                if changed:
                    raise ValueError(
                        f"{key}: cannot change {changed[0]} when resuming ({saved_flat.get(changed[0])!r} in the "
                        f"checkpoint); only trainer.* may differ"
                    )
    return validate(dataclasses.replace(saved, trainer=trainer))


# ------------------------------------------------------------------------------------------------ the loop


@dataclass
class TrainResult:
    run_dir: Path
    epochs: int
    global_step: int
    history: list[dict[str, float]]
    """Per epoch trained in this call: the scalars written (TensorBoard tag -> value)."""
    stopped: str | None = None
    """Why the run stopped before ``trainer.epochs`` (a stop signal; ``freeform.preemption``), None if it did not.
    ``checkpoints/last.pt`` then holds epoch ``epochs``, and the same command continues the run."""
    stop_signal: int | None = None
    """The stop signal this process received (None: none, or only another rank did)."""


def _agree(dp: Any, signalled: bool, failed: bool) -> tuple[bool, bool]:
    """Whether any rank was signalled to stop / failed to write: every rank stops at the same epoch boundary even
    when a signal reached rank 0 alone (one small all-reduce per epoch; the identity in one process)."""
    flags = dp.sum_(torch.tensor([int(signalled), int(failed)], dtype=torch.int64))
    return bool(flags[0] > 0), bool(flags[1] > 0)


def _write_failure(what: Path, exc: OSError, run_dir: Path, saved_epoch: int | None) -> str:
    """One line: what could not be written, why, and what the run directory still holds."""
    where = what.relative_to(run_dir) if what.is_relative_to(run_dir) else what
    where = where if str(where) != "." else f"the run directory {run_dir}"
    kept = (f"{CHECKPOINT_DIR}/{LAST} still holds the state after {saved_epoch} epochs and loads"
            if saved_epoch is not None else "no checkpoint was written yet (the run starts afresh)")
    reason = f"[Errno {exc.errno}] {exc.strerror}" if exc.errno and exc.strerror else (str(exc) or type(exc).__name__)
    return (f"could not write {where}: {type(exc).__name__} {reason}; stopped cleanly, {kept}; free the space or "
            f"fix the mount, then run the same command again (trainer.resume=auto) or trainer.resume={run_dir}")


def _checkpoint_state(cfg: TrainConfig, ppo: Any, collector: EpisodeCollector) -> dict[str, Any]:
    """A run checkpoint: PPO's own (``PPO.load`` reads it) plus the run's config, records cursor and global RNGs.
    A collective in a data-parallel run (the state is gathered)."""
    return {
        **ppo.checkpoint(),
        "config": to_container(cfg),
        "collector": collector.state_dict(),
        "rng": capture_rng_state(),
        "freeform": freeform.__version__,
        "saved_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def train(
    cfg: TrainConfig,
    run_dir: str | Path,
    *,
    overrides: Sequence[str] | None = None,
    callbacks: Sequence[EpochCallback] | None = None,
) -> TrainResult:
    """Train (or, with ``cfg.trainer.resume``, continue) a run in ``run_dir``; see the module docstring.

    ``callbacks`` run after every epoch (default: :func:`default_callbacks`). Returns the run's :class:`TrainResult`.

    Inside a process group of several ranks (``torchrun``; :func:`freeform.agents.distributed.init_from_env`) every
    rank calls this: each builds its slice of the environments on its own device, PPO is data-parallel, and only
    rank 0 writes the run directory (its ``run_dir`` is used by all), logs, records, checkpoints and runs the
    callbacks; the other ranks return an empty history. With ``trainer.dry_run`` nothing is built: the per-rank
    split is printed and an empty result returned.
    """
    cfg = validate(cfg)
    run_dir = Path(distributed.broadcast_object(str(run_dir)))  # rank 0's, on every rank
    if cfg.trainer.dry_run:
        from freeform.launch import describe_split

        if distributed.is_main_process():
            print(describe_split(cfg, distributed.world_size()), flush=True)
        return TrainResult(run_dir=run_dir, epochs=0, global_step=0, history=[])
    main_rank = distributed.is_main_process()
    state: dict[str, Any] | None = None
    ckpt_path: Path | None = None
    if cfg.trainer.resume == AUTO:
        # This run directory's own checkpoint, if any (rank 0 looks: its directory is everyone's).
        found = auto_checkpoint(run_dir) if main_rank else None
        found = distributed.broadcast_object(str(found) if found is not None else None)
        ckpt_path = Path(found) if found is not None else None
        if ckpt_path is None:
            log.info("trainer.resume=auto: no %s/%s in %s, starting a new run", CHECKPOINT_DIR, LAST, run_dir)
    elif cfg.trainer.resume:
        ckpt_path = resolve_checkpoint(cfg.trainer.resume)
    if ckpt_path is not None:
        # Read the checkpoint before anything in the run directory is opened: a bad file loses nothing.
        state = load_checkpoint(ckpt_path)
        try:
            saved = from_container(state["config"])
        except (ValueError, KeyError) as exc:
            raise CheckpointError(f"checkpoint {ckpt_path}: its config is unusable: {exc}") from exc
        cfg = resume_config(saved, cfg, overrides)
        log.info("resuming %s from %s (epoch %d, step %d)", run_dir, ckpt_path, state["epoch"], state["global_step"])

    if cfg.trainer.threads:
        torch.set_num_threads(cfg.trainer.threads)
    device = resolve_device(cfg.trainer.device, cfg.name)
    env, policy, ppo = build(cfg, device, distributed.env_slice(cfg.env.num_envs, distributed.world_size(), distributed.rank()))
    collector = EpisodeCollector()
    if state is not None:
        ppo.load_state_dict(state["ppo"] if cfg.algo.name == "ppo" else state["evolution"])  # data-parallel: each rank takes its slice of the saved environments
        collector.load_state_dict(state["collector"])
        restore_rng_state(state["rng"])

    ckpt_dir = run_dir / CHECKPOINT_DIR
    logger: Logger | None = None
    if main_rank:
        # A new run in a directory a killed attempt wrote events to (trainer.resume=auto, no last.pt yet): drop them.
        stale_events = state is None and any(run_dir.glob("events.out.tfevents.*"))
        run_dir.mkdir(parents=True, exist_ok=True)
        info_path = run_dir / RUN_INFO
        if state is None:
            _write_json(info_path, run_info(cfg, device))
        else:
            info = json.loads(info_path.read_text()) if info_path.is_file() else run_info(cfg, device)
            info.setdefault("resumes", []).append(
                {
                    "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "epoch": ppo.epoch,
                    "device": str(device),
                    "world_size": distributed.world_size(),
                }
            )
            _write_json(info_path, info)

        logger = Logger(
            run_dir,
            total_epochs=cfg.trainer.epochs,
            initial_epoch=min(ppo.epoch, cfg.trainer.epochs),
            purge_step=ppo.global_step + 1 if state is not None else (0 if stale_events else None),
            progress=cfg.trainer.progress,
            print_every=cfg.trainer.print_every,
        )
    callbacks = list(default_callbacks(cfg) if callbacks is None else callbacks)
    history: list[dict[str, float]] = []
    stop = preemption.StopSignals(cfg.trainer.stop_grace_s)
    stopped: str | None = None
    failure: str | None = None  # rank 0's first failed write: the run stops at the next epoch boundary
    saved_epoch = ppo.epoch if state is not None else None  # what checkpoints/last.pt holds
    done = (ppo.epoch, ppo.global_step)  # epochs and steps of the last complete epoch
    try:
        with stop:
            if state is None:
                if logger is not None:
                    container = to_container(cfg)
                    logger.log_config(
                        OmegaConf.to_yaml(container),
                        flatten(container),
                        {"charts/episode_reward_mean": 0.0, "charts/episode_reward_max": 0.0},
                    )
                    logger.flush()
                if cfg.trainer.checkpoint_every:  # the untrained policy (the "untrained critic" of Fig. 5)
                    with stop.writing():
                        ckpt = _checkpoint_state(cfg, ppo, collector)  # data-parallel: a collective, every rank
                        if main_rank:
                            path = ckpt_dir / numbered_name(0)
                            try:
                                save_checkpoint(path, ckpt)
                            except OSError as exc:
                                failure = _write_failure(path, exc, run_dir, saved_epoch)
            time_checkpoint = 0.0
            while True:
                # The epoch boundary: every rank learns whether any was signalled or failed to write.
                signalled, failed = _agree(ppo.dp, stop.requested, failure is not None)
                if failed:
                    break
                if ppo.epoch >= cfg.trainer.epochs:
                    break
                if signalled:
                    stopped = preemption.signal_name(stop.signum) if stop.signum is not None else "a signal to another rank"
                    break
                try:
                    with stop.epoch():
                        stats = dict(ppo.train_epoch())
                        # The task's own figures of the epoch's scoring (LocomotionTask: perf/sim_seconds, ...).
                        if isinstance(env.task, ReportsStats):
                            stats.update(ppo.dp.reduce_stats(env.task.stats))
                        epoch = ppo.epoch - 1
                        t0 = time.perf_counter()
                        # The records and body metrics are of the global batch: every rank's episodes.
                        if cfg.algo.name == "ppo":
                            rollout, episode_infos = ppo.dp.gather_rollout(ppo.rollout, ppo.episode_infos)
                        else:  # a generation of evolution is already a batch of finished episodes
                            rollout, episode_infos = None, ppo.episode_infos
                        if logger is not None:
                            try:
                                _log_epoch(cfg, run_dir, ppo, logger, collector, callbacks, history, rollout,
                                           episode_infos, epoch, stats, t0, time_checkpoint)
                            except _EpochWriteError as exc:
                                failure = _write_failure(exc.path, exc.cause, run_dir, saved_epoch)
                except preemption.EpochAbandoned:
                    # PPO's state is half-way through the epoch: nothing more is written, last.pt stays as it was.
                    log.warning("epoch %d abandoned: it did not finish within trainer.stop_grace_s=%g s of %s",
                                done[0], cfg.trainer.stop_grace_s, preemption.signal_name(stop.signum or 0))
                    stopped = f"{preemption.signal_name(stop.signum or 0)} (epoch in progress abandoned)"
                    break
                t1 = time.perf_counter()
                with stop.writing():
                    ckpt = _checkpoint_state(cfg, ppo, collector)  # data-parallel: a collective, every rank
                    if main_rank and failure is None:  # never a checkpoint past an epoch whose files are missing
                        path = ckpt_dir / LAST
                        try:
                            save_checkpoint(path, ckpt)
                            saved_epoch = ppo.epoch
                            if cfg.trainer.checkpoint_every and ppo.epoch % cfg.trainer.checkpoint_every == 0:
                                path = ckpt_dir / numbered_name(ppo.epoch)
                                save_checkpoint(path, ckpt)
                        except OSError as exc:
                            failure = _write_failure(path, exc, run_dir, saved_epoch)
                time_checkpoint = time.perf_counter() - t1
                if failure is None:  # ranks > 0 take rank 0's write as done: a failure stops all at the next boundary
                    saved_epoch = ppo.epoch
                done = (ppo.epoch, ppo.global_step)
    finally:
        if logger is not None:
            try:
                logger.close()  # flushes TensorBoard
            except OSError as exc:
                if failure is None:
                    raise
                log.warning("could not flush TensorBoard events either: %s", exc)
    if failure is not None or (stopped is None and done[0] < cfg.trainer.epochs):
        raise CheckpointWriteError(failure or "stopped: rank 0 could not write the run's files (its log says which)")
    if stopped is not None:
        kept = f"{CHECKPOINT_DIR}/{LAST} holds the state after {saved_epoch} epochs" if saved_epoch is not None else (
            "no checkpoint was written yet")
        log.warning("stopped on %s, %d of %d epochs done; %s: the same command continues the run "
                    "(trainer.resume=auto), or trainer.resume=%s", stopped, saved_epoch or 0, cfg.trainer.epochs,
                    kept, run_dir)
        done = (saved_epoch or 0, done[1])
    return TrainResult(run_dir=run_dir, epochs=done[0], global_step=done[1], history=history,
                       stopped=stopped, stop_signal=stop.signum)


class _EpochWriteError(Exception):
    """An OSError while writing an epoch's record or events, with the file it concerned."""

    def __init__(self, path: Path, cause: OSError) -> None:
        super().__init__(f"{path}: {cause}")
        self.path, self.cause = path, cause


def _log_epoch(
    cfg: TrainConfig,
    run_dir: Path,
    ppo: Any,
    logger: Logger,
    collector: EpisodeCollector,
    callbacks: Sequence[EpochCallback],
    history: list[dict[str, float]],
    rollout: Any,
    episode_infos: list[dict[str, Any]],
    epoch: int,
    stats: dict[str, float],
    t0: float,
    time_checkpoint: float,
) -> None:
    """Rank 0's writing of an epoch before its checkpoint: the design record, the scalars, the callbacks, a flush —
    so that whatever the checkpoint claims is on disk. An OSError becomes an :class:`_EpochWriteError` naming the
    file (the record, or the run directory for TensorBoard's events and the callbacks' files)."""
    episodes = collector.collect(rollout, episode_infos) if rollout is not None else ppo.episodes()
    body = {k: float(np.mean(v)) for k, v in episodes["metrics"].items()} if episodes else {}
    if episodes is not None and cfg.trainer.record_designs:
        record = EpochRecord(
            epoch=epoch,
            global_step=ppo.global_step,
            actions=episodes["actions"],
            final_grids=episodes["final_grids"],
            rewards=episodes["rewards"],
            values=episodes["values"],
            metrics=episodes["metrics"],
        )
        try:
            write_record(run_dir, record)
        except OSError as exc:
            raise _EpochWriteError(record_path(run_dir, epoch), exc) from exc
    stats["time_logging"] = time.perf_counter() - t0
    stats["time_checkpoint"] = time_checkpoint  # the previous epoch's: this one's is not taken yet
    try:
        history.append(logger.log_epoch(epoch, ppo.global_step, stats, body))
        ctx = EpochContext(epoch, ppo.global_step, stats, episodes, cfg, run_dir, logger, ppo)
        for callback in callbacks:
            callback(ctx)
        # Everything up to this step is on disk before a checkpoint says the run got this far.
        logger.flush()
    except OSError as exc:
        raise _EpochWriteError(run_dir, exc) from exc


# ------------------------------------------------------------------------------------------------ Hydra CLI


def _secondary_rank_dir() -> Path:
    """Where Hydra may put a rank > 0's own output (its log, before it is silenced): a scratch directory, removed
    at the end; the run directory is rank 0's, and its timestamp could differ from this rank's by a second."""
    return Path(tempfile.gettempdir()) / f"freeform-rank{distributed.launch_rank()}-{os.getpid()}"


def _resolver_run_dir(resume: str | None, default: str) -> str:
    """``hydra.run.dir``: the resumed run's directory (``trainer.resume=<run or file>``), else ``default``
    (runs/<experiment>/<timestamp>, or what ``hydra.run.dir`` says: ``trainer.resume=auto`` continues whatever
    directory that is); a scratch directory on ranks > 0 of a data-parallel run (rank 0's run directory is
    broadcast to them)."""
    if distributed.launch_rank() > 0:
        return str(_secondary_rank_dir())
    return str(run_dir_of(resume)) if resume and resume != AUTO else default


def _resolver_hydra_subdir(resume: str | None, output_dir: str | None = None) -> str | None:
    """``hydra.output_subdir``: keep the original run's ``.hydra`` when resuming in its directory (an explicit
    ``trainer.resume``, or ``auto`` where the job's directory ``output_dir`` has a checkpoint); none on ranks > 0
    of a data-parallel run (rank 0 writes it)."""
    if distributed.launch_rank() > 0:
        return None
    if resume == AUTO:
        resuming = output_dir is not None and auto_checkpoint(output_dir) is not None
    else:
        resuming = bool(resume)
    return f".hydra/resume_{datetime.now():%Y-%m-%d_%H-%M-%S}" if resuming else ".hydra"


SWEPT_KEYS_ENV = "FREEFORM_SWEPT_KEYS"


def _swept_keys(argv: Sequence[str]) -> set[str]:
    """The keys a command line sweeps over (``seed=0,1,2`` -> ``{"seed"}``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides([a for a in argv if not a.startswith("-")])
        return {o.key_or_group for o in parsed if o.is_sweep_override()}
    except Exception:  # an argument Hydra's grammar rejects: Hydra itself reports it
        return set()


def _resolver_sweep_subdir(job_overrides: Sequence[str], exclude: Sequence[str]) -> str:
    """``hydra.sweep.subdir``: the job's values of the *swept* keys, e.g. ``seed=3`` for ``-m seed=0,1,2,3,4``.

    Hydra's ``override_dirname`` names every override, swept or not; which keys are swept is read from the command
    line (``sys.argv``) — or from ``FREEFORM_SWEPT_KEYS``, which :func:`main` sets for jobs that run in other
    processes (the submitit launchers). Without a sweep, every override except ``exclude`` names the job.
    """
    if SWEPT_KEYS_ENV in os.environ:
        swept = {k for k in os.environ[SWEPT_KEYS_ENV].split(",") if k}
    else:
        swept = _swept_keys(sys.argv[1:])
    keys = [(_override_key(o), o) for o in job_overrides]
    chosen = [o for k, o in keys if k in swept] or [o for k, o in keys if k not in set(exclude)]
    return ",".join(sorted(chosen)).replace("/", "_") or "default"


OmegaConf.register_new_resolver("freeform_sweep_subdir", _resolver_sweep_subdir, replace=True)
OmegaConf.register_new_resolver("freeform_run_dir", _resolver_run_dir, replace=True)
OmegaConf.register_new_resolver("freeform_hydra_subdir", _resolver_hydra_subdir, replace=True)
register_configs()


def _hydra_entry(cfg: Any) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from tqdm.contrib.logging import logging_redirect_tqdm

    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    try:
        typed = to_dataclass(cfg)
        # torchrun / a multi-task SLURM step: join the process group (rank r on GPU r); ranks > 0 stay quiet.
        if not typed.trainer.dry_run and distributed.init_from_env() and not distributed.is_main_process():
            _silence_secondary_rank()
        with logging_redirect_tqdm():
            result = train(typed, run_dir, overrides=list(hydra_cfg.overrides.task))
        if hydra_cfg.mode != RunMode.MULTIRUN or result.stopped:  # a sweep's next job in this process reuses the group
            distributed.shutdown()  # every rank finished: tear the process group down together
    except (ValueError, CheckpointError) as exc:
        # A clear one-line message (and a non-zero exit), not a traceback through Hydra's internals.
        raise SystemExit(f"freeform-train: error: {exc}") from exc
    if result.stopped:
        # Stopped by a signal, checkpoint written: exit 75 "requeue me" (or submitit's handler requeues the job).
        preemption.exit_for_requeue(result.stop_signal)
    if not distributed.is_main_process() or typed.trainer.dry_run:
        return
    log.info("done: %d epochs, %d steps, run directory %s", result.epochs, result.global_step, run_dir)
    curve = [h["charts/episode_reward_mean"] for h in result.history if "charts/episode_reward_mean" in h]
    if len(curve) >= 2:
        last = curve[-min(5, len(curve) - 1) :]
        first, tail = curve[0], sum(last) / len(last)
        log.info(
            "episode reward mean: first epoch of this call %.2f -> last %d epochs %.2f (x%.2f)",
            first, len(last), tail, tail / first if first else float("nan"),
        )


def _silence_secondary_rank() -> None:
    """A rank > 0 logs warnings to the console only: rank 0 writes the run's log."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if isinstance(handler, logging.FileHandler):
            root.removeHandler(handler)
            handler.close()
    root.setLevel(logging.WARNING)
    scratch = _secondary_rank_dir()
    if scratch.is_dir():
        shutil.rmtree(scratch, ignore_errors=True)


def _dry_run_requested(argv: Sequence[str]) -> bool:
    return any(a.split("=", 1)[0].lstrip("+") == "trainer.dry_run" and a.split("=", 1)[1].lower() in ("true", "1", "yes")
               for a in argv if "=" in a)


def main() -> None:
    """Console entry point ``freeform-train`` (Hydra parses ``sys.argv``).

    ``trainer.dry_run=true`` on the command line is answered here, before Hydra launches anything (a sweep on the
    submitit launcher would submit jobs): the jobs, each one's per-rank split and the launch command are printed.
    """
    import hydra

    # conf/hydra/launcher/submitit_*.yaml carry the names the plugin registers its typed schemas under, so Hydra
    # checks them against those schemas (what we want) and warns that such matching is deprecated.
    warnings.filterwarnings(
        "ignore", message=r"\s*'hydra/launcher/submitit_\w+' is validated against ConfigStore schema", category=UserWarning
    )
    # Jobs of the submitit launchers resolve hydra.sweep.subdir in their own processes, whose argv is submitit's.
    os.environ[SWEPT_KEYS_ENV] = ",".join(sorted(_swept_keys(sys.argv[1:])))
    if _dry_run_requested(sys.argv[1:]):
        from freeform.launch import dry_run

        text = dry_run(sys.argv[1:], CONF_DIR)
        if distributed.launch_rank() == 0:
            print(text, flush=True)
        return

    hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")(_hydra_entry)()


if __name__ == "__main__":
    main()
