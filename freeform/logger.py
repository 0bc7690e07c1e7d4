"""TensorBoard scalars and a tqdm bar for a training run.

Tags follow CleanRL's layout, at the global step (environment steps over all environments):

- ``charts/`` episode statistics: ``episode_reward_mean``, ``_max``, ``_min``, ``episodes``, ``episode_length_mean``
- ``losses/`` the PPO update: ``policy_loss``, ``value_loss``, ``approx_kl``, ``kl_coeff``, ``entropy``,
  ``clip_fraction``, ``explained_variance``
- ``policy/`` the Gaussian policy's spread (names containing ``std``/``sigma``)
- ``perf/`` speed: ``samples_per_second``, ``time_*`` seconds (including the trainer's own ``time_logging``)
- ``body/<metric>`` the mean over the epoch's designs of every body metric (``freeform.body``)
- ``stats/`` any other number PPO reports

A resumed run opens a new writer in the same directory with ``purge_step`` = the checkpoint's global step + 1, so
TensorBoard drops whatever the killed run logged after its checkpoint: one curve, no gap, no duplicate.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import torch
from torch.utils.tensorboard import SummaryWriter
from torch.utils.tensorboard.summary import hparams as hparams_summary
from tqdm.auto import tqdm

log = logging.getLogger("freeform.train")

CHARTS = ("episode_reward_mean", "episode_reward_max", "episode_reward_min", "episodes", "episode_length_mean",
          "eval_return", "eval_return_std", "eval_length_mean")
SKIP = ("epoch", "global_step")  # already the x-axis (the step) and the bar
LOSSES = (
    "policy_loss",
    "value_loss",
    "entropy_loss",
    "kl_loss",
    "total_loss",
    "approx_kl",
    "kl",
    "kl_coeff",
    "entropy",
    "clip_fraction",
    "explained_variance",
    "grad_norm",
    "lr",
)


def tag_for(name: str) -> str:
    """TensorBoard tag of a PPO statistic (module docstring)."""
    if "/" in name:
        return name
    if name in CHARTS:
        return f"charts/{name}"
    if name in LOSSES:
        return f"losses/{name}"
    if name.startswith("time_") or name.endswith("per_second") or name in ("sps", "fps"):
        return f"perf/{name}"
    if "std" in name or "sigma" in name:
        return f"policy/{name}"
    return f"stats/{name}"


class ScalarSink(Protocol):
    """Where a learner's per-epoch statistics may go (``PPO(..., logger=...)``): :class:`Logger` is one, and so is
    any object with this method (a dict-appender in a notebook, a wandb bridge)."""

    def log(self, stats: Mapping[str, Any], step: int) -> None: ...


def _scalars(stats: Mapping[str, Any]) -> dict[str, float]:
    """The finite numbers of ``stats`` under their TensorBoard tags (``tag_for``); the x-axis keys left out."""
    written: dict[str, float] = {}
    for name, value in stats.items():
        if name in SKIP:
            continue
        number = _number(value)
        if number is not None and math.isfinite(number):
            written[tag_for(name)] = number
    return written


def _number(value: Any) -> float | None:
    if isinstance(value, torch.Tensor):
        if value.numel() != 1:
            return None
        value = value.item()
    if isinstance(value, bool | int | float):
        return float(value)
    try:  # numpy scalars
        return float(value)
    except (TypeError, ValueError):
        return None


def _hparam_value(value: Any) -> int | float | str | bool:
    if isinstance(value, bool | int | float | str):
        return value
    return str(value)


def _wait_for_a_later_event_file_second(run_dir: Path) -> None:
    """Make sure the new event file sorts after every existing one.

    TensorBoard reads a directory's event files in name order, and a name is
    ``events.out.tfevents.<unix seconds>.<host>.<pid>.<writer counter>``. A resumed run's writer created in the same
    second as an earlier one (a quick resume in the same process, as in the tests) could sort *before* it (counter
    "10" < "9"), and then its ``purge_step`` would be applied before the old events are read. Waiting for the
    next second (at most one, and only when such a file exists) keeps the order = the order of writing.
    """
    stamps = []
    for f in run_dir.glob("events.out.tfevents.*"):
        try:
            stamps.append(int(f.name.split(".")[3]))
        except (IndexError, ValueError):
            continue
    if stamps:
        latest = max(stamps)
        while int(time.time()) <= latest:
            time.sleep(0.05)


class Logger:
    """TensorBoard writer plus a tqdm bar over epochs for one run directory.

    ``purge_step``: when resuming, the checkpoint's global step + 1 (events from a killed run at or after it are
    dropped by TensorBoard). ``initial_epoch`` / ``total_epochs`` position the bar.
    """

    def __init__(
        self,
        run_dir: str | os.PathLike[str],
        *,
        total_epochs: int,
        initial_epoch: int = 0,
        purge_step: int | None = None,
        progress: bool = True,
        print_every: int = 0,
        console_metrics: tuple[str, ...] = ("volume", "lcc_ratio"),
    ) -> None:
        self.run_dir = Path(run_dir)
        _wait_for_a_later_event_file_second(self.run_dir)
        self.writer = SummaryWriter(log_dir=str(self.run_dir), purge_step=purge_step)
        self.print_every = print_every
        self.console_metrics = console_metrics
        self.bar = tqdm(
            total=total_epochs,
            initial=initial_epoch,
            desc="epochs",
            unit="epoch",
            disable=not progress,
            dynamic_ncols=True,
        )

    def log_config(self, config_yaml: str, hparams: Mapping[str, Any], metrics: Mapping[str, float]) -> None:
        """The resolved config as text (``config``) and the hyper-parameters for TensorBoard's HPARAMS tab.

        The hparams summary goes into this run's own event file (not a sub-run, as ``add_hparams`` would do),
        linked to the ``metrics`` tags (e.g. ``charts/episode_reward_mean``).
        """
        # Four-space indentation makes TensorBoard's markdown render the YAML verbatim.
        self.writer.add_text("config", "\n".join("    " + line for line in config_yaml.splitlines()), 0)
        exp, ssi, sei = hparams_summary({k: _hparam_value(v) for k, v in hparams.items()}, dict(metrics))
        for summary in (exp, ssi, sei):
            self.writer.file_writer.add_summary(summary)  # type: ignore[union-attr]

    def log_epoch(
        self,
        epoch: int,
        global_step: int,
        stats: Mapping[str, Any],
        body: Mapping[str, float],
    ) -> dict[str, float]:
        """Write the epoch's scalars at ``global_step``, advance the bar, log a line every ``print_every`` (through
        ``logging``: the console and the run's log file; run the loop inside ``tqdm.contrib.logging.logging_redirect_tqdm``
        so lines and the bar don't collide).

        ``epoch`` is the 0-based index of the epoch just trained. Returns the scalars written (tag -> value).
        """
        written = _scalars(stats)
        for name, value in body.items():
            written[f"body/{name}"] = float(value)
        for tag, number in written.items():
            self.writer.add_scalar(tag, number, global_step)
        mean = written.get("charts/episode_reward_mean", float("nan"))
        best = written.get("charts/episode_reward_max", float("nan"))
        sps = written.get("perf/samples_per_second", float("nan"))
        self.bar.set_postfix(reward=f"{mean:.2f}", max=f"{best:.1f}", sps=f"{sps:.0f}", refresh=False)
        self.bar.update(1)
        if self.print_every and ((epoch + 1) % self.print_every == 0 or epoch == 0):
            parts = [f"epoch {epoch + 1}", f"step {global_step}", f"reward mean {mean:.2f} max {best:.1f}"]
            if "charts/eval_return" in written:
                parts.append(f"eval return {written['charts/eval_return']:.2f}")
            parts += [f"{name} {body[name]:.3g}" for name in self.console_metrics if name in body]
            parts.append(f"{sps:.0f} samples/s")
            log.info(" | ".join(parts))
        return written

    def log(self, stats: Mapping[str, Any], step: int) -> None:
        """A :class:`ScalarSink`: ``stats``' numbers to TensorBoard at ``step`` (no bar, no console line)."""
        for tag, number in _scalars(stats).items():
            self.writer.add_scalar(tag, number, step)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.bar.close()
        self.writer.close()


__all__ = ["Logger", "ScalarSink", "tag_for"]
