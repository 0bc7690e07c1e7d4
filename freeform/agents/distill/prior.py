"""A prior policy's log-likelihood as a reward: teachers regularised towards a student (``control.prior``, issue 56).

Distral (Teh et al., NeurIPS 2017) trains each task's policy π_i with the reward r + c·log π₀(a | s), π₀ a policy
shared by every task, so that the tasks' policies stay where one policy can follow them all; with PPO's entropy
bonus the added term is a one-sample estimate of −c·KL(π_i ‖ π₀) plus entropy. Here π₀ is a distilled student
(frozen) and π_i a body's teacher in a bank: teachers trained apart each find their own gait (a student takes all
of it on their bodies and none on others, ``docs/control.md``), teachers regularised towards the student keep
gaits it can share.

The term is the prior's log-density of the action taken per entry that acts (a masked Gaussian's mask; else every
entry), ``c · log π₀(a | s) / n_a``, so that c means the same for a body of 10 muscles and one of 60. It is added
to the env's reward. The return the run logs stays the task's: at an episode's end ``info["task_reward"]`` is the
env's own rewards summed over the episode (the shaped-reward convention of ``freeform.envs.dense``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.networks.observation_groups import POLICY
from freeform.distributions import MaskedDiagGaussian


class PriorReward:
    """A ``VecEnv`` whose reward gains ``coeff · log π₀(a | s) / n_a`` (module docstring): ``prior`` a policy on
    the env's observations (``forward(obs) -> (*params, value)`` in ``prior.distribution``), ``s`` the observation
    the action was taken on — the env's ``observation`` (a control env's: the one it last returned, also after
    ``load_state_dict``), or its ``"policy"`` group. Everything else is the env's."""

    def __init__(self, env: Any, prior: nn.Module, coeff: float) -> None:
        if not (isinstance(coeff, (int, float)) and coeff > 0):
            raise ValueError(f"control.prior_coeff must be > 0 (the weight of the prior's log-likelihood), got {coeff!r}")
        if getattr(prior, "distribution", None) is None:
            raise ValueError(f"the prior {type(prior).__name__} declares no action distribution (a controller's "
                             "distribution attribute)")
        self.env, self.prior, self.coeff = env, prior.eval(), float(coeff)
        for p in self.prior.parameters():
            p.requires_grad_(False)
        self.num_envs, self.action_dim, self.device = env.num_envs, env.action_dim, env.device
        self.observation_shape = env.observation_shape
        self._task_return = torch.zeros(env.num_envs, device=env.device)
        """The env's own rewards since each episode began (a control env's episodes all end at an epoch's end, where
        a checkpoint is taken: nothing to save)."""

    def __getattr__(self, name: str) -> Any:
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(self, seed: int | None = None) -> Any:
        self._task_return.zero_()
        return self.env.reset(seed)

    @torch.no_grad()
    def log_likelihood(self, obs: Any, actions: torch.Tensor) -> torch.Tensor:
        """``log π₀(a | s) / n_a`` ``[N]`` (float32) for ``actions [N, A]`` taken on ``obs``."""
        own = obs[POLICY] if isinstance(obs, Mapping) else obs
        *params, _ = self.prior(own)
        dist = self.prior.distribution
        actions = actions.to(params[0].device, params[0].dtype).reshape(self.num_envs, -1)
        acting = (params[2].sum(-1) if isinstance(dist, MaskedDiagGaussian)
                  else torch.full_like(params[0][:, 0], actions.shape[1]))
        return (dist.log_prob(tuple(params), actions) / acting.clamp_min(1)).float()

    def step(self, actions: torch.Tensor) -> tuple[Any, torch.Tensor, torch.Tensor, dict[str, Any]]:
        if self.env.observation is None:
            raise RuntimeError("call reset() before step()")
        bonus = self.coeff * self.log_likelihood(self.env.observation, actions).to(self.device)
        obs, reward, done, info = self.env.step(actions)
        self._task_return = self._task_return + reward.to(self._task_return.dtype)
        info = {**info, "task_reward": torch.where(done, self._task_return, 0.0)}
        self._task_return = torch.where(done, 0.0, self._task_return)
        return obs, reward + bonus.to(reward.dtype), done, info


__all__ = ["PriorReward"]
