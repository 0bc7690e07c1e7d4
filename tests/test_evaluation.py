"""Periodic deterministic evaluation in the training app: ``agent.eval_every`` -> ``charts/eval_return``."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import run_cli as cli  # tests/helpers.py
from helpers import scalars, tiny

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py


def test_eval_every_logs_eval_return_to_tensorboard_and_console(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    run = tmp_path / "run"
    cli(monkeypatch, *tiny("trainer.print_every=1", "trainer.record_designs=false"), "trainer.epochs=4",
        "agent.eval_every=2", "agent.eval_episodes=4", f"hydra.run.dir={run}")
    tags = scalars(run)
    steps = [s for s, _ in tags["charts/episode_reward_mean"]]
    assert [s for s, _ in tags["charts/eval_return"]] == [steps[1], steps[3]]  # after epochs 2 and 4
    assert all(v >= 0 for _, v in tags["charts/eval_return"])  # the volume of a deterministic design
    lines = [line for line in (run / "train.log").read_text().splitlines() if "| reward mean" in line]
    assert len(lines) == 4 and ["eval return" in line for line in lines] == [False, True, False, True]
