"""The trainer: one loop for every learner (``freeform.learner.Learner``), read top to bottom in :meth:`Trainer.run`.

Each epoch the learner trains (PPO: a rollout and an update; evolution: a generation), then the trainer writes the
epoch — its finished episodes as a design record, its scalars to TensorBoard, the per-epoch callbacks (renders), a
flush — and only then checkpoints, so whatever a checkpoint claims is already on disk and a run killed at any moment
resumes from its last checkpoint with no gap. On SIGTERM/SIGUSR2 (a cluster's preemption) the epoch in progress
finishes, the run checkpoints and reports ``stopped`` (``freeform.preemption``); a failed write stops the run
cleanly (``freeform.run.rundir``).

Inside a process group of several ranks (``torchrun``) every rank runs the trainer: each builds its slice of the
environments, the learner is data-parallel, and only rank 0 writes the run directory, logs, records, checkpoints
and runs the callbacks; the other ranks return an empty history.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

import freeform
from freeform import preemption
from freeform.agents import distributed
from freeform.checkpoint import (
    CHECKPOINT_DIR,
    LAST,
    CheckpointWriteError,
    capture_rng_state,
    restore_rng_state,
)
from freeform.config import TrainConfig, flatten, to_container, validate
from freeform.envs.base import ReportsStats
from freeform.learner import Episodes, Learner
from freeform.logger import Logger
from freeform.records import EpochRecord, placed
from freeform.run.build import build, control_env, resolve_device
from freeform.run.resume import find_checkpoint, read_checkpoint
from freeform.run.rundir import RunDir

log = logging.getLogger("freeform.train")


@dataclass
class EpochContext:
    """What a per-epoch callback sees, after the epoch's scalars are written and before its checkpoint.

    ``epoch``: 0-based index of the epoch just trained; ``global_step``: environment steps so far (the TensorBoard
    step); ``episodes``: the epoch's finished episodes as written to its design record (``freeform.learner``:
    ``final_grids [E, ρ, ρ, ρ] uint8``, ``rewards [E]``, ``actions [E, T, A]``, ``values [E, T]``, ``metrics``
    {name: [E]}, ``infos``: the environment's own info dicts, ``bodies`` ...) or None.
    """

    epoch: int
    global_step: int
    stats: dict[str, float]
    episodes: Episodes | None
    cfg: TrainConfig
    run_dir: Path
    logger: Logger
    learner: Learner


EpochCallback = Callable[[EpochContext], None]


def _names_teachers(env: Any) -> bool:
    """Whether ``env``'s observations name each body's teacher (a bank's, ``agents.teachers.TeacherIndex``): what a
    learner acting on it reads, so that a render drives its policy on the same kind of observation."""
    from freeform.agents.distill.teachers import TEACHER

    shape = env.observation_shape
    return isinstance(shape, dict) and TEACHER in shape


def render_callback(every: int) -> EpochCallback:
    """At epochs 0, ``every``, 2·``every``, ... log renders of the epoch's bodies to TensorBoard
    (``freeform.render.log_bodies(writer, final_grids, rewards, step, cfg)``: best, median and a random body; in a
    control run ``log_controlled_gait``: the controller driving the best body)."""

    def callback(ctx: EpochContext) -> None:
        if ctx.episodes is None or ctx.epoch % every:  # epochs 0, every, 2·every, ...
            return
        try:
            from freeform.render import log_bodies
        except ImportError as exc:
            raise ValueError("trainer.render_every > 0 needs freeform.render.log_bodies, not available") from exc
        grids = placed(ctx.episodes["final_grids"], ctx.episodes.get("yaw"))  # as each body was scored
        if ctx.cfg.control is None:
            log_bodies(ctx.logger.writer, grids, ctx.episodes["rewards"], ctx.global_step, ctx.cfg)
            return
        # a control run: the bodies' images, and the policy's mode driving a body (co-design: designing it first)
        from freeform.render import log_controlled_gait, log_epoch_renders

        log_epoch_renders(ctx.logger.writer, grids, ctx.episodes["rewards"], ctx.global_step,
                          np.random.default_rng([ctx.cfg.seed, ctx.global_step]))
        learner, cfg = ctx.learner, ctx.cfg
        if cfg.control.codesign:  # the policy's mode designs a body and drives it
            env = control_env(cfg, learner.device, (0, 1), ctx.global_step)
        else:  # the controller drives the epoch's best body, in the box it was built for
            best = grids[int(ctx.episodes["rewards"].argmax())][None]
            env = control_env(cfg, learner.device, (0, 1), ctx.global_step, bodies=best, box=learner.env.box)
            if cfg.control.teachers and not _names_teachers(learner.env):  # (a student reads the body alone)
                env = env.env
        log_controlled_gait(ctx.logger.writer, env, learner.episode_actor(deterministic=True), ctx.global_step)

    return callback


def default_callbacks(cfg: TrainConfig) -> list[EpochCallback]:
    """The callbacks a run gets from its config (``trainer.render_every``)."""
    return [render_callback(cfg.trainer.render_every)] if cfg.trainer.render_every else []


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
    converged: int | None = None
    """The epoch after which the run's curve had stopped improving (``trainer.plateau_window`` on
    ``trainer.plateau_on``'s curve: :func:`flattened`): the run ended there, before ``trainer.epochs``; None where it
    did not."""


def plateaued(curve: Sequence[float], window: int, gain: float) -> bool:
    """Whether a training curve (a return per epoch) has stopped improving: the mean of its last ``window`` epochs
    is less than ``gain`` (relative) above the mean of the ``window`` before them. Needs 2 × ``window`` epochs;
    ``window`` 0 is never."""
    if window <= 0 or len(curve) < 2 * window:
        return False
    last, before = np.mean(curve[-window:]), np.mean(curve[-2 * window: -window])
    return bool(last - before < gain * abs(before))


def flattened(cfg: TrainConfig, returns: Sequence[float], evaluated: Sequence[Sequence[float]] = (),
              epoch: int | None = None) -> bool:
    """Whether a run of ``cfg`` had stopped improving by its own rule after ``epoch`` epochs (None: all it has):
    :func:`plateaued` with ``trainer.plateau_window`` and ``plateau_gain`` on ``trainer.plateau_on``'s curve —
    ``returns`` (the training return per epoch) or ``evaluated`` (``(epoch, eval_return)`` pairs, one every
    ``agent.eval_every`` epochs, a window of ``plateau_window`` epochs holding ``plateau_window / eval_every``)."""
    t = cfg.trainer
    if not t.plateau_window:  # (no rule: nor an evaluation to divide by, e.g. fit's recipes)
        return False
    if t.plateau_on == "eval_return":
        points = [float(v) for e, v in evaluated if epoch is None or e <= epoch]
        return plateaued(points, t.plateau_window // cfg.agent.eval_every, t.plateau_gain)
    return plateaued(list(returns)[:epoch], t.plateau_window, t.plateau_gain)


class Trainer:
    """One run of ``cfg`` in ``run_dir`` (module docstring); :meth:`run` trains it.

    ``overrides``: Hydra's command-line overrides (what a resume may change); ``callbacks`` run after every epoch
    (default: :func:`default_callbacks`)."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, overrides: Sequence[str] | None = None,
                 callbacks: Sequence[EpochCallback] | None = None) -> None:
        self.run_dir = run_dir
        # Read the checkpoint before anything in the run directory is opened: a bad file loses nothing.
        ckpt = find_checkpoint(cfg, run_dir)
        self.resumed: dict[str, Any] | None = None
        if ckpt is not None:
            self.resumed, cfg = read_checkpoint(ckpt, cfg, overrides)
            log.info("resuming %s from %s (epoch %d, step %d)", run_dir, ckpt, self.resumed["epoch"],
                     self.resumed["global_step"])
        self.cfg = cfg
        if cfg.trainer.threads:
            torch.set_num_threads(cfg.trainer.threads)
        self.device = resolve_device(cfg.trainer.device, cfg.name, cfg.agent.cuda_graph)
        lo, hi = distributed.env_slice(cfg.env.num_envs, distributed.world_size(), distributed.rank())
        self.env, self.learner = build(cfg, self.device, (lo, hi))
        self.collectives = distributed.collectives(hi - lo, self.device)
        if self.resumed is not None:
            self.learner.restore(self.resumed)  # data-parallel: each rank takes its slice of the saved environments
            restore_rng_state(self.resumed["rng"])
        self.callbacks = list(default_callbacks(cfg) if callbacks is None else callbacks)
        self.dir = RunDir(run_dir, distributed.is_main_process(),
                          saved_epoch=self.learner.epoch if self.resumed is not None else None)
        self.logger: Logger | None = None
        self.stop = preemption.StopSignals(cfg.trainer.stop_grace_s)
        self.stopped: str | None = None
        self.history: list[dict[str, float]] = []
        self.curve: list[float] = list((self.resumed or {}).get("return_curve", []))  # the training return per epoch
        # (epoch, eval_return) pairs: a plateau on eval_return reads them, and a resume must too
        self.evaluated: list[tuple[int, float]] = [(int(e), float(v)) for e, v in (self.resumed or {}).get(
            "eval_curve", [])]
        self.converged: int | None = None
        self.done = (self.learner.epoch, self.learner.global_step)  # epochs and steps of the last complete epoch
        self.time_checkpoint = 0.0

    # -- the run, top to bottom ----------------------------------------------------------------------------------

    def run(self) -> TrainResult:
        self.open_run_dir()
        try:
            with self.stop:
                self.write_start()
                while self.keep_going():
                    if not self.train_one_epoch():
                        break
                    self.checkpoint()
        finally:
            self.close_logger()
        return self.result()

    def open_run_dir(self) -> None:
        """Rank 0: ``run_info.json`` and the TensorBoard logger (a resume continues the curves with no gap)."""
        if not self.dir.writer:
            return
        cfg, learner, resumed = self.cfg, self.learner, self.resumed is not None
        # A new run in a directory a killed attempt wrote events to (trainer.resume=auto, no last.pt yet): drop them.
        stale_events = not resumed and self.dir.has_events()
        self.dir.write_info(cfg, self.device, learner.epoch if resumed else None)
        self.logger = Logger(self.run_dir, total_epochs=cfg.trainer.epochs,
                             initial_epoch=min(learner.epoch, cfg.trainer.epochs),
                             purge_step=learner.global_step + 1 if resumed else (0 if stale_events else None),
                             progress=cfg.trainer.progress, print_every=cfg.trainer.print_every)

    def write_start(self) -> None:
        """A new run: the config to TensorBoard, and the untrained learner as checkpoint 0 (the "untrained critic"
        of the paper's Fig. 5)."""
        if self.resumed is not None:
            return
        if self.logger is not None:
            container = to_container(self.cfg)
            self.logger.log_config(OmegaConf.to_yaml(container), flatten(container),
                                   {"charts/episode_reward_mean": 0.0, "charts/episode_reward_max": 0.0})
            self.logger.flush()
        if self.cfg.trainer.checkpoint_every:
            with self.stop.writing():
                self.dir.save_checkpoint(self.checkpoint_state(), 0, numbered=True, last=False)

    def keep_going(self) -> bool:
        """At an epoch boundary: on, unless any rank was signalled or failed to write, or the epochs are done (one
        small all-reduce, so that every rank stops at the same boundary; the identity in one process)."""
        flags = self.collectives.sum_(torch.tensor([int(self.stop.requested), int(self.dir.failure is not None)],
                                                   device=self.device))
        if bool(flags[1] > 0) or self.learner.epoch >= self.cfg.trainer.epochs:
            return False
        t = self.cfg.trainer
        if flattened(self.cfg, self.curve, self.evaluated):  # (the curves are global: every rank agrees)
            self.converged = self.learner.epoch
            what = "the training return" if t.plateau_on == "return" else "the evaluation's return"
            log.info("%s stopped improving: the last %d epochs added less than %g %% over the %d before; stopped at "
                     "epoch %d (trainer.plateau_window, plateau_on=%s)", what, t.plateau_window, 100 * t.plateau_gain,
                     t.plateau_window, self.converged, t.plateau_on)
            return False
        if bool(flags[0] > 0):
            self.stopped = preemption.signal_name(self.stop.signum) if self.stop.signum is not None else (
                "a signal to another rank")
            return False
        return True

    def train_one_epoch(self) -> bool:
        """Train an epoch and write it (:meth:`write_epoch`); False if a stop signal abandoned it half-way (the
        learner's state is then half an epoch on: nothing more is written, ``last.pt`` stays as it was)."""
        try:
            with self.stop.epoch():
                stats = dict(self.learner.train_epoch())
                if "episode_reward_mean" in stats:
                    self.curve.append(float(stats["episode_reward_mean"]))
                if "eval_return" in stats:  # (gathered over every rank by PPO: the same everywhere)
                    self.evaluated.append((self.learner.epoch, float(stats["eval_return"])))
                if isinstance(getattr(self.env, "task", None), ReportsStats):  # the task's own figures (LocomotionTask: sim seconds ...)
                    stats.update(self.collectives.reduce_stats(self.env.task.stats))
                t0 = time.perf_counter()
                episodes = self.learner.episodes()  # the global batch's (a collective)
                if self.logger is not None:
                    self.write_epoch(self.learner.epoch - 1, stats, episodes, t0)
        except preemption.EpochAbandoned:
            signal = preemption.signal_name(self.stop.signum or 0)
            log.warning("epoch %d abandoned: it did not finish within trainer.stop_grace_s=%g s of %s",
                        self.done[0], self.cfg.trainer.stop_grace_s, signal)
            self.stopped = f"{signal} (epoch in progress abandoned)"
            return False
        return True

    def write_epoch(self, epoch: int, stats: dict[str, float], episodes: Episodes | None, t0: float) -> None:
        """Rank 0's writing of an epoch before its checkpoint: the design record, the scalars, the callbacks, a
        flush — so that whatever the checkpoint claims is on disk."""
        learner, logger = self.learner, self.logger
        assert logger is not None
        if episodes is not None and self.cfg.trainer.record_designs:
            actions = episodes["actions"] if self.cfg.trainer.record_actions else episodes["actions"][:, :, :0]
            self.dir.write_record(EpochRecord(epoch=epoch, global_step=learner.global_step, actions=actions,
                                              final_grids=episodes["final_grids"], rewards=episodes["rewards"],
                                              values=episodes["values"], metrics=episodes["metrics"],
                                              yaw=episodes.get("yaw")))
            if self.dir.failure is not None:
                return
        body = {k: float(v.mean()) for k, v in episodes["metrics"].items()} if episodes else {}
        stats["time_logging"] = time.perf_counter() - t0
        stats["time_checkpoint"] = self.time_checkpoint  # the previous epoch's: this one's is not taken yet
        context = EpochContext(epoch, learner.global_step, stats, episodes, self.cfg, self.run_dir, logger, learner)
        self.dir.attempt(self.run_dir, lambda: self._log(context, body))

    def _log(self, context: EpochContext, body: dict[str, float]) -> None:
        logger = context.logger
        self.history.append(logger.log_epoch(context.epoch, context.global_step, context.stats, body))
        for callback in self.callbacks:
            callback(context)
        logger.flush()  # everything up to this step is on disk before a checkpoint says the run got this far

    def checkpoint(self) -> None:
        """``last.pt`` (and every ``checkpoint_every`` epochs a numbered one), never past an epoch whose files are
        missing. The state is gathered from every rank (a collective); rank 0 writes it."""
        t1 = time.perf_counter()
        epoch, every = self.learner.epoch, self.cfg.trainer.checkpoint_every
        with self.stop.writing():
            self.dir.save_checkpoint(self.checkpoint_state(), epoch, numbered=bool(every) and epoch % every == 0)
        self.time_checkpoint = time.perf_counter() - t1
        self.done = (epoch, self.learner.global_step)

    def checkpoint_state(self) -> dict[str, Any]:
        """A run checkpoint: the learner's own part plus the run's config and global RNGs."""
        return {
            **self.learner.checkpoint(),
            "config": to_container(self.cfg),
            "rng": capture_rng_state(),
            "return_curve": list(self.curve),
            "eval_curve": [list(point) for point in self.evaluated],
            "freeform": freeform.__version__,
            "saved_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }

    def close_logger(self) -> None:
        if self.logger is None:
            return
        try:
            self.logger.close()  # flushes TensorBoard
        except OSError as exc:
            if self.dir.failure is None:
                raise
            log.warning("could not flush TensorBoard events either: %s", exc)

    def result(self) -> TrainResult:
        """The run's outcome; a failed write is a ``CheckpointWriteError`` with its one-line reason."""
        cfg, saved = self.cfg, self.dir.saved_epoch
        finished = self.stopped is not None or self.converged is not None or self.done[0] >= cfg.trainer.epochs
        if self.dir.failure is not None or not finished:
            raise CheckpointWriteError(self.dir.failure or "stopped: rank 0 could not write the run's files (its log "
                                                           "says which)")
        epochs = self.done[0]
        if self.stopped is not None:
            kept = (f"{CHECKPOINT_DIR}/{LAST} holds the state after {saved} epochs" if saved is not None
                    else "no checkpoint was written yet")
            log.warning("stopped on %s, %d of %d epochs done; %s: the same command continues the run "
                        "(trainer.resume=auto), or trainer.resume=%s", self.stopped, saved or 0, cfg.trainer.epochs,
                        kept, self.run_dir)
            epochs = saved or 0
        return TrainResult(run_dir=self.run_dir, epochs=epochs, global_step=self.done[1], history=self.history,
                           stopped=self.stopped, stop_signal=self.stop.signum, converged=self.converged)


def train(cfg: TrainConfig, run_dir: str | Path, *, overrides: Sequence[str] | None = None,
          callbacks: Sequence[EpochCallback] | None = None) -> TrainResult:
    """Train (or, with ``cfg.trainer.resume``, continue) a run in ``run_dir`` (module docstring); returns its
    :class:`TrainResult`. With ``trainer.dry_run`` nothing is built: the per-rank split is printed."""
    cfg = validate(cfg)
    run_dir = Path(distributed.broadcast_object(str(run_dir)))  # rank 0's, on every rank
    if cfg.trainer.dry_run:
        from freeform.launch import describe_split

        if distributed.is_main_process():
            print(describe_split(cfg, distributed.world_size()), flush=True)
        return TrainResult(run_dir=run_dir, epochs=0, global_step=0, history=[])
    return Trainer(cfg, run_dir, overrides, callbacks).run()


__all__ = ["EpochCallback", "EpochContext", "TrainResult", "Trainer", "default_callbacks", "flattened", "plateaued",
           "render_callback", "train"]
