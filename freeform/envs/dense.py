"""Dense design rewards (the paper's discussion): score the partial body every ``every`` design steps with the task
and reward the improvement, for any task.

``DenseDesignReward(env, every)`` wraps a design ``VecEnv`` (``DesignEnv``): at every ``every``-th step of an
episode the current grids are scored by ``task.reward`` and the reward is the change of that score since the last
scoring; at the episode's end the reward is the terminal reward less the last score. The rewards of an episode
therefore sum to the sparse terminal reward (a potential-based shaping with γ = 1), which stays the default
(no wrapper). The terminal reward itself is kept in ``info["task_reward"]``.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["DenseDesignReward"]


class DenseDesignReward:
    """A ``VecEnv`` whose reward is the improvement of the task's score of the partial designs every ``every`` steps.

    env: the design env (observations are the grids, ``uint8 [N, ρ, ρ, ρ]``); task: what scores them (default
    ``env.task``). Per-environment state (``per_env``: the step in the episode and the last score) is
    checkpointed with the env's own when the env has ``state_dict``.
    """

    def __init__(self, env: Any, every: int, task: Any = None) -> None:
        if not (isinstance(every, int) and every >= 1):
            raise ValueError(f"every must be an integer >= 1, got {every!r}")
        self.env = env
        self.every = every
        self.task = task if task is not None else env.task
        self.num_envs = env.num_envs
        self.observation_shape = env.observation_shape
        self.action_dim = env.action_dim
        self.device = env.device
        self._step = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self._last = torch.zeros(self.num_envs, dtype=torch.float32, device=self.device)

    def __getattr__(self, name: str) -> Any:  # everything else (steps, resolution, ...) is the env's
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        self._step.zero_()
        self._last.zero_()
        return self.env.reset(seed)

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """``(obs, reward [N], done [N], info)``: reward = score(t) − score(last scoring) at scoring steps, the
        terminal reward − score(last scoring) at the end, 0 otherwise."""
        obs, reward, done, info = self.env.step(actions)
        self._step += 1
        dense = torch.zeros_like(self._last)
        score_now = (self._step % self.every == 0) & ~done
        if bool(score_now.any()):
            idx = torch.nonzero(score_now).flatten()
            score = self.task.reward(obs[idx]).to(self._last)
            dense[idx] = score - self._last[idx]
            self._last[idx] = score
        terminal = reward.to(self._last)
        dense = torch.where(done, terminal - self._last, dense)
        info = dict(info)
        info["task_reward"] = torch.where(done, terminal, torch.zeros_like(terminal))
        self._last = torch.where(done, torch.zeros_like(self._last), self._last)
        self._step = torch.where(done, torch.zeros_like(self._step), self._step)
        return obs, dense, done, info

    def state_dict(self) -> dict[str, Any]:
        inner = self.env.state_dict() if hasattr(self.env, "state_dict") else {}
        per_env = {**inner.get("per_env", {}), "dense_step": self._step.clone(), "dense_last": self._last.clone()}
        return {**inner, "per_env": per_env}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        per_env = dict(state.get("per_env", {}))
        self._step = per_env.pop("dense_step").to(self.device)
        self._last = per_env.pop("dense_last").to(self.device)
        if hasattr(self.env, "load_state_dict"):
            self.env.load_state_dict({**state, "per_env": per_env})
