"""Helpers shared by the tests that drive the training app (importable: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from freeform import train as train_mod


def run_cli(monkeypatch: pytest.MonkeyPatch, *args: str) -> None:
    """Run ``freeform-train *args`` in this process (argv and the swept-keys variable restored after the test)."""
    monkeypatch.setattr(sys, "argv", ["freeform-train", *args])
    monkeypatch.setenv(train_mod.SWEPT_KEYS_ENV, "")  # main() sets it for its jobs
    train_mod.main()


def scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar curve of a run directory's TensorBoard events: ``{tag: [(step, value), ...]}``."""
    acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}
