"""The Learner protocol is all the trainer needs: a toy learner of a few lines, registered by name, gets the run
directory, TensorBoard scalars, design records, checkpoints and an exact resume, with no change to the trainer
(the recipe in docs/architecture.md). PPO and every evolutionary method satisfy the same protocol."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers import scalars, tiny

from freeform.config import compose
from freeform.evolve import design_grids
from freeform.learner import Learner
from freeform.records import iter_records
from freeform.run import build, register_learner, train
from freeform.run.build import LEARNERS


class RandomSearch:
    """Each epoch N random design sequences, scored by the env's task; keeps the best score."""

    def __init__(self, env: Any, seed: int) -> None:
        self.env, self.epoch, self.best = env, 0, float("-inf")
        self.generator = torch.Generator().manual_seed(seed)
        self._episodes: dict[str, Any] | None = None

    @property
    def global_step(self) -> int:
        return self.epoch * self.env.num_envs * self.env.steps

    def train_epoch(self) -> dict[str, float]:
        actions = torch.randn(self.env.num_envs, self.env.steps, self.env.action_dim, generator=self.generator)
        rewards, info = self.env.score(design_grids(self.env, actions))
        self.epoch += 1
        self.best = max(self.best, float(rewards.max()))
        self._episodes = {"actions": actions.numpy(), "values": np.full(actions.shape[:2], np.nan, np.float32),
                          "rewards": rewards.float().numpy(), "final_grids": info["final_grids"].numpy(),
                          "metrics": {}, "infos": [info]}
        return {"episode_reward_mean": float(rewards.mean()), "best": self.best}

    def episodes(self) -> dict[str, Any] | None:
        return self._episodes

    def checkpoint(self) -> dict[str, Any]:
        return {"epoch": self.epoch, "global_step": self.global_step,
                "random_search": {"generator": self.generator.get_state(), "best": self.best}}

    def restore(self, checkpoint: dict[str, Any]) -> None:
        self.epoch = int(checkpoint["epoch"])
        self.generator.set_state(checkpoint["random_search"]["generator"])
        self.best = float(checkpoint["random_search"]["best"])


@pytest.fixture
def random_search():
    register_learner("random_search")(lambda cfg, env, device, envs: RandomSearch(env, cfg.seed))
    yield
    LEARNERS.pop("random_search")


def test_a_registered_toy_learner_runs_records_and_resumes_exactly(random_search: None, tmp_path: Path) -> None:
    cfg = compose(*tiny("trainer.epochs=3", "algo.name=random_search"))
    assert isinstance(build(cfg, torch.device("cpu"))[1], Learner)
    train(cfg, tmp_path / "straight")
    cfg.trainer.epochs = 2
    train(cfg, tmp_path / "split")
    cfg.trainer.epochs, cfg.trainer.resume = 3, str(tmp_path / "split")
    train(cfg, tmp_path / "split")
    straight, split = (list(iter_records(tmp_path / run)) for run in ("straight", "split"))
    assert [r.epoch for r in straight] == [r.epoch for r in split] == [0, 1, 2]
    for a, b in zip(straight, split, strict=True):
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.rewards, b.rewards)
    tags = scalars(tmp_path / "split")
    assert [s for s, _ in tags["stats/best"]] == [20, 40, 60]  # one curve across the resume: N·T = 4·5 per epoch
    assert tags["stats/best"][-1][1] == max(r.rewards.max() for r in straight)


def test_ppo_and_evolution_are_learners() -> None:
    for algo in ("ppo", "ga"):
        assert isinstance(build(compose(*tiny(f"algo.name={algo}")), torch.device("cpu"))[1], Learner)


def test_the_config_validates_learner_names_without_importing_the_app() -> None:
    """The registry lives in freeform.learner, below the config and the app: validating a config imports no part of
    freeform.run (a subprocess, to see a fresh sys.modules), and once the app is imported every one of freeform's own
    names has its builder."""
    import subprocess
    import sys

    from freeform import learner
    from freeform.evolve.config import ALGORITHMS

    code = ("import sys; from freeform.config import TrainConfig, validate; validate(TrainConfig()); "
            "print(sorted(m for m in sys.modules if m.startswith('freeform.run')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    assert LEARNERS is learner.LEARNERS and set(ALGORITHMS) <= set(LEARNERS)


class Curve(RandomSearch):
    """RandomSearch whose reported return follows a set curve: it rises by 1 an epoch for 8 epochs, then flat."""

    def train_epoch(self) -> dict[str, float]:
        stats = super().train_epoch()
        return {**stats, "episode_reward_mean": 10.0 + min(self.epoch, 8)}


def test_a_run_stops_where_its_training_curve_flattens_and_stays_stopped(tmp_path: Path) -> None:
    """``trainer.plateau_window=3``: the return 11, 12, …, 18, 18, …; epoch 12 is the first whose last 3 epochs
    (18, 18, 18) add less than 2 % over the 3 before (17, 18, 18: +1.9 %; at epoch 11, over 16, 17, 18: +5.9 %). The
    run ends there (of 40), says so, and a resume goes no further; the pure rule is checked on its own too."""
    from freeform.run.trainer import plateaued

    assert not plateaued([1.0, 2.0, 3.0], 2, 0.02) and not plateaued([5.0] * 7, 0, 0.02)
    assert plateaued([5.0] * 4, 2, 0.02) and not plateaued([1.0, 1.0, 2.0, 2.0], 2, 0.02)
    assert plateaued([-2.0, -2.0, -1.99, -1.99], 2, 0.02) and not plateaued([-2.0, -2.0, -1.0, -1.0], 2, 0.02)
    register_learner("curve")(lambda cfg, env, device, envs: Curve(env, cfg.seed))
    try:
        cfg = compose(*tiny("trainer.epochs=40", "algo.name=curve", "trainer.plateau_window=3"))
        result = train(cfg, tmp_path / "run")
        assert (result.epochs, result.converged) == (12, 12)
        again = train(cfg, tmp_path / "run")  # (resumed: the curve is in the checkpoint)
        assert (again.epochs, again.converged, again.history) == (12, 12, [])
    finally:
        LEARNERS.pop("curve")


def test_the_evaluated_plateau_reads_windows_of_whole_evaluations_up_to_an_epoch() -> None:
    """``trainer.plateau_on=eval_return``, one evaluation every 10 epochs, a window of 20 epochs (2 evaluations):
    flat where the last two points add < 2 % over the two before, whatever the training return does; ``epoch``
    reads the points up to it. A window of part of an evaluation, or no evaluation, is refused naming the key."""
    from freeform.run.trainer import flattened

    cfg = compose(*tiny("agent.eval_every=10", "trainer.plateau_on=eval_return", "trainer.plateau_window=20"))
    flat, rising = [5.0] * 60, [float(e) for e in range(1, 61)]  # (training returns that say the opposite)
    points = [(10, 1.0), (20, 2.0), (30, 3.0), (40, 3.0), (50, 3.0), (60, 3.0)]
    assert not flattened(cfg, flat, points[:4]) and flattened(cfg, rising, points)
    assert not flattened(cfg, rising, points, epoch=50) and flattened(cfg, rising, points, epoch=60)
    by_return = compose(*tiny("agent.eval_every=10", "trainer.plateau_window=20"))
    assert flattened(by_return, flat, points[:4]) and not flattened(by_return, rising, points)
    with pytest.raises(ValueError, match="trainer.plateau_window must be a multiple of agent.eval_every=10"):
        compose(*tiny("agent.eval_every=10", "trainer.plateau_on=eval_return", "trainer.plateau_window=15"))
    with pytest.raises(ValueError, match="set agent.eval_every"):
        compose(*tiny("trainer.plateau_on=eval_return", "trainer.plateau_window=20"))
    with pytest.raises(ValueError, match="which a distillation or evolution does not run"):
        compose(*tiny("agent.eval_every=10", "trainer.plateau_on=eval_return", "trainer.plateau_window=20",
                      "algo.name=ga"))
    with pytest.raises(ValueError, match="trainer.plateau_on must be one of"):
        compose(*tiny("trainer.plateau_on=evaluation"))
    no_rule = compose(*tiny("trainer.plateau_on=eval_return"))  # (no window, no evaluation: accepted, never flat)
    assert not flattened(no_rule, flat, points)
