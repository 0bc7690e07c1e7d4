"""Evolution behind the trainer's one loop: :class:`Evolution` is a ``freeform.learner.Learner`` (``train_epoch()``,
``episodes()``, ``epoch``, ``global_step``, ``checkpoint()``/``restore()``), as PPO is, so ``freeform-train algo=ga``
gets the same run directory, TensorBoard tags, design records, checkpoints, resume and preemption as PPO.

An epoch is one generation: the optimiser's ``N = env.num_envs`` genomes are scored in one batch by
``DesignEnv.score`` (what the last step of PPO's rollout calls: the same task and simulator) — action sequences
after their T bundles are placed by the design rule, grids directly — and the scores are told back. Its cost is N
scored designs, what a PPO epoch with ``rollout_steps = T`` costs; ``global_step`` advances by N·T as PPO's does,
so TensorBoard curves of both line up at equal designs.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
import torch

from freeform.envs.untrained import design_grids
from freeform.learner import Episodes


class Optimizer(Protocol):
    """An evolutionary optimiser: ``genome`` is ``"actions"`` (``ask() -> [N, T, A]`` float) or ``"grids"``
    (``ask() -> [N, ρ, ρ, ρ]`` uint8); ``tell(fitness [N])`` with higher = better."""

    genome: str

    def ask(self) -> torch.Tensor: ...

    def tell(self, fitness: torch.Tensor) -> None: ...

    def stats(self) -> dict[str, float]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu").numpy()


class Evolution:
    """One evolutionary optimiser on a design env, a ``freeform.learner.Learner`` (module docstring); one process.

    After ``train_epoch()``: :meth:`episodes` is the generation as finished episodes (``actions [N, T, A]`` — the
    genomes; ``[N, 0, A]`` for grid genomes —, ``values [N, T]`` NaN (no critic), ``rewards [N]``, ``final_grids``,
    ``metrics``, ``infos``: the env's info of the generation).
    """

    def __init__(self, env: Any, optimizer: Optimizer, name: str) -> None:
        self.env, self.optimizer, self.name = env, optimizer, name
        self.num_envs = env.num_envs
        self.epoch = 0
        self.best = float("-inf")
        """The best reward scored so far."""
        self._episodes: Episodes | None = None

    def train_epoch(self) -> dict[str, float]:
        """Score one generation and breed the next; return its statistics (PPO's names where they mean the same)."""
        t0 = time.perf_counter()
        genomes = self.optimizer.ask()
        if self.optimizer.genome == "actions":  # the grids the sequences design, scored as an episode's last step
            grids, actions = design_grids(self.env, genomes), genomes
        else:
            grids, actions = genomes.to(self.env.device), torch.zeros((len(genomes), 0, self.env.action_dim))
        rewards, info = self.env.score(grids)
        t1 = time.perf_counter()
        self.optimizer.tell(rewards)
        t2 = time.perf_counter()
        n, steps = self.num_envs, self.env.steps
        self.epoch += 1
        self.best = max(self.best, float(rewards.max()))
        self._episodes = {
            "actions": _np(actions.to(torch.float32)),
            "values": np.full(actions.shape[:2], np.nan, dtype=np.float32),
            "rewards": _np(rewards.to(torch.float32)),
            "final_grids": _np(info["final_grids"]).astype(np.uint8),
            "metrics": {k: _np(torch.as_tensor(v)).astype(np.float32) for k, v in (info.get("metrics") or {}).items()},
            "yaw": _np(info["yaw"]).astype(np.int8) if "yaw" in info else np.zeros(n, np.int8),
            "infos": [info],
        }
        return {
            "episode_reward_mean": float(rewards.mean()),
            "episode_reward_max": float(rewards.max()),
            "episode_reward_min": float(rewards.min()),
            "episodes": float(n),
            "charts/best_reward": self.best,
            "charts/designs_scored": float(self.designs),
            "time_rollout": t1 - t0,
            "time_update": t2 - t1,
            "samples_per_second": n * steps / max(t2 - t0, 1e-9),
            "epoch": float(self.epoch),
            "global_step": float(self.global_step),
            **self.optimizer.stats(),
        }

    @property
    def designs(self) -> int:
        """Designs scored so far (N per generation): the cost unit of the comparison with PPO."""
        return self.epoch * self.num_envs

    @property
    def global_step(self) -> int:
        """Design steps so far, N·T per generation, as a PPO epoch of ``rollout_steps = T`` counts them."""
        return self.epoch * self.num_envs * self.env.steps

    def episodes(self) -> Episodes | None:
        """The last generation as finished episodes (class docstring); None before the first."""
        return self._episodes

    def state_dict(self) -> dict[str, Any]:
        return {"name": self.name, "epoch": self.epoch, "global_step": self.global_step, "designs": self.designs,
                "best": self.best, "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("name") != self.name:
            raise ValueError(f"the state is of algo.name={state.get('name')!r}, this run's is {self.name!r}")
        self.optimizer.load_state_dict(state["optimizer"])
        self.epoch, self.best = int(state["epoch"]), float(state["best"])

    def checkpoint(self) -> dict[str, Any]:
        """A run checkpoint's learner part: the algorithm, counters and ``evolution`` state."""
        return {"algo": self.name, "epoch": self.epoch, "global_step": self.global_step, "evolution": self.state_dict()}

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Continue from a run checkpoint :meth:`checkpoint` wrote."""
        if "evolution" not in checkpoint:
            raise ValueError(f"the checkpoint holds no evolution state (it is of algo {checkpoint.get('algo', 'ppo')!r})")
        self.load_state_dict(checkpoint["evolution"])


__all__ = ["Evolution", "Optimizer", "design_grids"]
