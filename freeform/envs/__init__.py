"""Batched environments: the VecEnv and Task protocols, the design environment and its tasks, and the closed-loop
control environment (a controller sets every voxel's actuation each control period), and the two in one episode
(co-design: design steps, then control steps on the body just built).

``from_gymnasium`` / ``to_gymnasium`` (``freeform.envs.adapters``) need the optional ``gym`` extra; they are imported
on first use, so the core install never imports Gymnasium.
"""

from typing import Any

from freeform.envs.base import ReportsPlacement, ReportsStats, StatefulVecEnv, Task, VecEnv
from freeform.envs.codesign import CodesignEnv
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.envs.dense import DenseDesignReward
from freeform.envs.design import DesignEnv, EnvConfig
from freeform.envs.population import PopulationControlEnv
from freeform.envs.tasks import ControlledLocomotionTask, LocomotionTask, VolumeTask
from freeform.envs.trajectory import TrajectoryTask, trajectory_reward

__all__ = [
    "VecEnv", "StatefulVecEnv", "Task", "ReportsStats", "ReportsPlacement", "DesignEnv", "EnvConfig", "VolumeTask", "LocomotionTask", "ControlledLocomotionTask",
    "TrajectoryTask", "trajectory_reward", "DenseDesignReward", "ControlEnv", "ControlConfig", "CodesignEnv",
    "PopulationControlEnv",
    "from_gymnasium",
    "to_gymnasium",
]

_ADAPTERS = ("from_gymnasium", "to_gymnasium")


def __getattr__(name: str) -> Any:
    if name in _ADAPTERS:
        try:
            from freeform.envs import adapters
        except ImportError as exc:  # pragma: no cover - the gym extra is missing
            raise ImportError(f"freeform.envs.{name} needs Gymnasium: pip install 'freeform[gym]' ({exc})") from exc
        return getattr(adapters, name)
    raise AttributeError(f"module 'freeform.envs' has no attribute {name!r}")
