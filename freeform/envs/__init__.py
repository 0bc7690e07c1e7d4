"""Batched environments: the VecEnv and Task protocols, the design environment and its tasks."""

from freeform.envs.base import ReportsStats, StatefulVecEnv, Task, VecEnv
from freeform.envs.design import DesignEnv
from freeform.envs.tasks import LocomotionTask, VolumeTask

__all__ = ["VecEnv", "StatefulVecEnv", "Task", "ReportsStats", "DesignEnv", "VolumeTask", "LocomotionTask"]
