"""Helpers shared by the tests that drive the training app (importable: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from freeform import train as train_mod

TINY = {
    "env.num_envs": 4,
    "env.resolution": 6,
    "env.steps": 5,
    "agent.hidden": 16,
    "agent.num_sgd_iter": 2,
    "agent.sgd_minibatch_size": 8,
    "trainer.progress": "false",
    "trainer.print_every": 0,
    "trainer.checkpoint_every": 1,
    "trainer.threads": 1,
    "trainer.device": "cpu",
}
"""A training run of a few seconds (4 envs of 6³ grids, 5 steps, a 16-wide network), as command-line values."""


def tiny(*overrides: str) -> list[str]:
    """The tiny run's command-line overrides, with ``key=value`` overrides replacing (or adding to) its own."""
    values: dict[str, object] = dict(TINY)
    for override in overrides:
        key, value = override.split("=", 1)
        values[key] = value
    return [f"{k}={v}" for k, v in values.items()]


def run_cli(monkeypatch: pytest.MonkeyPatch, *args: str) -> None:
    """Run ``freeform-train *args`` in this process (argv and the swept-keys variable restored after the test)."""
    monkeypatch.setattr(sys, "argv", ["freeform-train", *args])
    monkeypatch.setenv(train_mod.SWEPT_KEYS_ENV, "")  # main() sets it for its jobs
    train_mod.main()


def straight_and_resumed(cfg: Any, root: Path, epochs: int) -> tuple[Path, Path]:
    """The resume tests' two runs of ``cfg``: ``epochs`` epochs straight in ``root/straight``, and ``epochs − 1`` then
    one more resumed from its checkpoint in ``root/split``. Returns the two run directories (``cfg.trainer`` is left
    as the resume set it)."""
    straight, split = root / "straight", root / "split"
    cfg.trainer.epochs = epochs
    train_mod.train(cfg, straight)
    cfg.trainer.epochs = epochs - 1
    train_mod.train(cfg, split)
    cfg.trainer.epochs, cfg.trainer.resume = epochs, str(split)
    train_mod.train(cfg, split)
    return straight, split


def learned_straight_and_resumed(build: Any, env: Any, path: Path, epochs: int) -> tuple[Any, Any]:
    """The library-level resume check: ``build()`` (a fresh ``PPO``) learns ``epochs`` epochs straight; another
    learns ``epochs − 1``, is saved to ``path`` and loaded onto ``env()`` (a fresh env), and learns one more. Asserts
    the two policies' weights equal to the bit; returns (straight, resumed) for the caller's own checks."""
    from freeform.agents import PPO

    straight = build()
    straight.learn(epochs)
    first = build()
    first.learn(epochs - 1)
    first.save(path)
    resumed = PPO.load(path, env())
    resumed.learn(1)
    for a, b in zip(straight.policy.parameters(), resumed.policy.parameters(), strict=True):
        assert torch.equal(a, b)
    return straight, resumed


def scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar curve of a run directory's TensorBoard events: ``{tag: [(step, value), ...]}``."""
    acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


class SingleView(gym.Env):
    """A one-environment ``to_gymnasium`` vector env seen as a ``gymnasium.Env``, for Gymnasium's env checker."""

    def __init__(self, vector_env: Any) -> None:
        self.vector_env = vector_env
        self.observation_space = vector_env.single_observation_space
        self.action_space = vector_env.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):  # type: ignore[override]
        super().reset(seed=seed)
        obs, info = self.vector_env.reset(seed=seed)
        return obs[0], info

    def step(self, action: np.ndarray):  # type: ignore[override]
        obs, reward, terminated, truncated, info = self.vector_env.step(action[None])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), {}
