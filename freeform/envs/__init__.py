"""Batched environments: the VecEnv protocol, the design environment and its tasks."""

from freeform.envs.base import Task, VecEnv
from freeform.envs.design import DesignEnv
from freeform.envs.tasks import LocomotionTask, VolumeTask

__all__ = ["VecEnv", "Task", "DesignEnv", "VolumeTask", "LocomotionTask"]
