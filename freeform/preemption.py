"""Stopping a run cleanly on the signals a cluster sends before it kills a job, so that the job can be requeued.

SLURM sends ``SIGUSR2`` before a job's time limit (``--signal=USR2@120``, what submitit asks for), and ``SIGTERM``
when it preempts or cancels a job (``torchrun`` and ``kill`` send ``SIGTERM`` too). While :func:`freeform.train.train`
runs, a :class:`StopSignals` catches both:

- the **first** signal asks for a stop: the epoch in progress is finished (its record, scalars and checkpoint are
  written) and the loop ends at that epoch boundary; every rank of a data-parallel run agrees to stop at the same
  boundary (the trainer sums the requests over ranks once per epoch). If the epoch cannot finish within
  ``trainer.stop_grace_s`` seconds of the signal (0: not at all) it is *abandoned* (:class:`EpochAbandoned`): the
  loop ends without writing anything more, and ``checkpoints/last.pt`` stays the previous epoch's. A signal that
  arrives while a checkpoint is being written lets the write finish.
- a **second** signal exits at once (:class:`StopNow`, a ``SystemExit``): a checkpoint being written is dropped
  (the atomic writer removes its temporary file), so ``last.pt`` is the last complete one.

The process then exits with :data:`REQUEUE_EXIT_CODE` (75, ``EX_TEMPFAIL`` of ``sysexits.h``: "temporary failure,
try again") — the run is consistent on disk and the same command continues it (``trainer.resume=auto``). Under
submitit, whose handler was the one in place before training started, that handler is called once the run has
stopped (:func:`exit_for_requeue`): for ``SIGUSR2`` it pickles the job again, requeues it and exits (submitit's
own exit codes: 144 with the local executor, 255 after ``scontrol requeue`` on SLURM).
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from collections.abc import Iterator
from types import FrameType
from typing import Any

log = logging.getLogger("freeform.train")

REQUEUE_EXIT_CODE = 75
"""Exit status of a run stopped by a signal with its last checkpoint intact: requeue it (``os.EX_TEMPFAIL``)."""

STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGUSR2") if hasattr(signal, name)
)
"""What SLURM, submitit and torchrun send before they kill a job (SIGUSR2 does not exist on Windows)."""


class EpochAbandoned(BaseException):  # noqa: N818 - an event, not an error; BaseException: `except Exception` keeps out
    """The grace period after a stop signal ran out before the epoch in progress finished."""


class StopNow(SystemExit):  # noqa: N818
    """A second stop signal: leave at once (exit status :data:`REQUEUE_EXIT_CODE`)."""

    def __init__(self) -> None:
        super().__init__(REQUEUE_EXIT_CODE)


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class StopSignals:
    """Catch :data:`STOP_SIGNALS` while a run trains (a context manager; the previous handlers come back on exit).

    ``grace_s``: how long the epoch in progress may take after the first signal before it is abandoned (0: at once).
    The trainer marks what it is doing with :meth:`epoch` (training, records, scalars: may be abandoned) and
    :meth:`writing` (the checkpoint: finished whatever comes, except a second signal). ``signum`` is the first
    signal received (None: none). Handlers can only be installed from the main thread; elsewhere (a run inside a
    worker thread) nothing is caught and a warning says so.
    """

    def __init__(self, grace_s: float) -> None:
        self.grace_s = float(grace_s)
        self.signum: int | None = None
        self._phase = "idle"
        self._deadline: float | None = None
        self._previous: dict[int, Any] = {}
        self._alarm_previous: Any = None

    @property
    def requested(self) -> bool:
        return self.signum is not None

    # -- installing ----------------------------------------------------------------------------------------------

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is not threading.main_thread():
            log.warning("training outside the main thread: SIGTERM/SIGUSR2 will not stop it cleanly")
            return self
        for sig in STOP_SIGNALS:
            self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def __exit__(self, *exc: object) -> None:
        self._disarm()
        for sig, handler in self._previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()

    # -- what the trainer is doing -------------------------------------------------------------------------------

    @contextlib.contextmanager
    def epoch(self) -> Iterator[None]:
        """Training an epoch and writing its record and scalars: abandoned when the grace period runs out."""
        self._phase = "epoch"
        try:
            if self.signum is not None:  # asked before this epoch began (the trainer checks first; kept for safety)
                self._start_grace()
            yield
        finally:
            self._phase = "idle"
            self._disarm()

    @contextlib.contextmanager
    def writing(self) -> Iterator[None]:
        """Writing the epoch's checkpoint: a first signal waits for it; only a second one interrupts it."""
        self._disarm()
        self._phase = "writing"
        try:
            yield
        finally:
            self._phase = "idle"

    # -- handlers ------------------------------------------------------------------------------------------------

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None:
            log.warning("%s again: exiting now; checkpoints/last.pt is the last complete checkpoint", signal_name(signum))
            raise StopNow()
        self.signum = signum
        if self._phase == "epoch":
            log.warning("%s: finishing the epoch in progress (at most %g s), then checkpointing and stopping",
                        signal_name(signum), self.grace_s)
            self._start_grace()
        elif self._phase == "writing":
            log.warning("%s: stopping once this checkpoint is written", signal_name(signum))
        else:
            log.warning("%s: stopping at the next epoch boundary", signal_name(signum))

    def _start_grace(self) -> None:
        if self.grace_s <= 0:
            raise EpochAbandoned()
        if self._deadline is not None:
            return
        self._deadline = time.monotonic() + self.grace_s
        if hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread():
            self._alarm_previous = signal.signal(signal.SIGALRM, self._on_alarm)
            signal.setitimer(signal.ITIMER_REAL, self.grace_s)

    def _on_alarm(self, signum: int, frame: FrameType | None) -> None:
        if self._phase == "epoch":
            raise EpochAbandoned()

    def _disarm(self) -> None:
        if self._deadline is None:
            return
        self._deadline = None
        if hasattr(signal, "setitimer"):
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self._alarm_previous if self._alarm_previous is not None else signal.SIG_DFL)
        self._alarm_previous = None


def exit_for_requeue(signum: int | None) -> None:
    """Leave the process after a clean stop: hand the signal to the handler that was in place before training (under
    submitit, ``SIGUSR2`` -> checkpoint the job and requeue it; that handler exits itself), else exit with
    :data:`REQUEUE_EXIT_CODE`. Call it after :class:`StopSignals` has put the previous handlers back."""
    if signum is not None:
        handler = signal.getsignal(signum)
        if callable(handler):
            handler(signum, None)  # submitit: requeues and exits; SIGTERM under submitit: only logged
    raise SystemExit(REQUEUE_EXIT_CODE)


__all__ = [
    "REQUEUE_EXIT_CODE",
    "STOP_SIGNALS",
    "EpochAbandoned",
    "StopNow",
    "StopSignals",
    "exit_for_requeue",
    "signal_name",
]
