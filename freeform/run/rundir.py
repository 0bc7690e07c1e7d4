"""A run's directory as rank 0 writes it — ``run_info.json``, ``checkpoints/``, ``records/`` — with one failure
policy (the layout: ``docs/training.md``).

The policy: a write that fails (disk full, quota, a vanished mount: an ``OSError``) is never a traceback mid-run.
The first one is kept as a one-line reason (:attr:`RunDir.failure`: what, why, and what the directory still holds);
no checkpoint is written after it, so ``checkpoints/last.pt`` never claims an epoch whose files are missing; the
trainer stops every rank at the next epoch boundary and raises ``CheckpointWriteError`` with the reason.
"""

from __future__ import annotations

import json
import platform
import socket
import subprocess
import sys
import uuid
from collections.abc import Callable
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch

import freeform
from freeform.agents import distributed
from freeform.checkpoint import CHECKPOINT_DIR, LAST, numbered_name, save_checkpoint
from freeform.config import TrainConfig
from freeform.files import copy_atomically, write_atomically
from freeform.records import EpochRecord, record_path, write_record
from freeform.sim import runtime as sim_runtime

RUN_INFO = "run_info.json"


class RunDir:
    """The run directory ``path``; only the main rank (``writer``) writes, the others' calls do nothing.

    ``saved_epoch``: the epoch ``checkpoints/last.pt`` holds (None: none yet); ``failure``: the first failed
    write's one-line reason (module docstring)."""

    def __init__(self, path: Path, writer: bool, saved_epoch: int | None = None) -> None:
        self.path, self.writer, self.saved_epoch = path, writer, saved_epoch
        self.failure: str | None = None

    def attempt(self, what: Path, write: Callable[[], Any]) -> bool:
        """Run ``write`` (on the main rank); an ``OSError`` becomes :attr:`failure` naming ``what``. Whether it
        succeeded (True on the other ranks)."""
        if not self.writer:
            return True
        try:
            write()
        except OSError as exc:
            self.fail(what, exc)
            return False
        return True

    def fail(self, what: Path, exc: OSError) -> None:
        """Keep the first failure's one line: what could not be written, why, what the directory still holds."""
        if self.failure is not None:
            return
        where = what.relative_to(self.path) if what.is_relative_to(self.path) else what
        where = where if str(where) != "." else f"the run directory {self.path}"
        kept = (f"{CHECKPOINT_DIR}/{LAST} still holds the state after {self.saved_epoch} epochs and loads"
                if self.saved_epoch is not None else "no checkpoint was written yet (the run starts afresh)")
        reason = f"[Errno {exc.errno}] {exc.strerror}" if exc.errno and exc.strerror else (str(exc) or type(exc).__name__)
        self.failure = (f"could not write {where}: {type(exc).__name__} {reason}; stopped cleanly, {kept}; free the "
                        f"space or fix the mount, then run the same command again (trainer.resume=auto) or "
                        f"trainer.resume={self.path}")

    # -- what a run writes -------------------------------------------------------------------------------------

    def write_info(self, cfg: TrainConfig, device: torch.device, resumed_epoch: int | None) -> None:
        """``run_info.json``: what made the run (:func:`run_info`); a resume appends to its ``resumes``."""
        if not self.writer:
            return
        self.path.mkdir(parents=True, exist_ok=True)
        path = self.path / RUN_INFO
        if resumed_epoch is None:
            info = run_info(cfg, device)
        else:
            info = json.loads(path.read_text()) if path.is_file() else run_info(cfg, device)
            info.setdefault("resumes", []).append({"time": _now(), "epoch": resumed_epoch, "device": str(device),
                                                   "world_size": distributed.world_size()})
        text = json.dumps(info, indent=2, default=str) + "\n"
        write_atomically(path, lambda f: f.write(text.encode()))

    def save_checkpoint(self, state: dict[str, Any], epoch: int, numbered: bool, last: bool = True) -> None:
        """``checkpoints/last.pt`` (``last``) and, with ``numbered``, ``checkpoints/epoch_<epoch>.pt`` — never
        after a failure. Every rank then takes the epoch as saved (a failure stops all at the next boundary)."""
        if self.failure is not None:
            return
        directory = self.path / CHECKPOINT_DIR
        if last:
            if not self.attempt(directory / LAST, lambda: save_checkpoint(directory / LAST, state)):
                return
            self.saved_epoch = epoch
        if numbered:  # (a copy of last.pt's bytes when it was just written: one serialisation)
            name = numbered_name(epoch)
            self.attempt(directory / name, lambda: copy_atomically(directory / LAST, directory / name) if last
                         else save_checkpoint(directory / name, state))

    def write_record(self, record: EpochRecord) -> None:
        """``records/epoch_<e>.npz`` (``freeform.records``)."""
        self.attempt(record_path(self.path, record.epoch), lambda: write_record(self.path, record))

    def has_events(self) -> bool:
        """TensorBoard event files are here (a killed attempt's, when no checkpoint was written)."""
        return any(self.path.glob("events.out.tfevents.*"))


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# ------------------------------------------------------------------------------------------------ provenance


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
        "run_id": uuid.uuid4().hex,  # (a run's identity: two runs of one process can start in one second)
        "start_time": _now(),
        "hostname": socket.gethostname(),
        "command": sys.argv,
        "experiment": cfg.name,
        "seed": cfg.seed,
        "world_size": distributed.world_size(),
        "resumes": [],
    }


__all__ = ["RUN_INFO", "RunDir", "run_info"]
