"""Batched environments: the VecEnv protocol, the design environment and its tasks."""

from freeform.envs.base import Task, VecEnv

__all__ = ["VecEnv", "Task"]
