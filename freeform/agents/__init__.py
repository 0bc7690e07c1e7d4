"""Agents: a hand-written batched PPO and its actor-critic networks.

``PPO(env, policy, PPOConfig(...))`` trains any ``freeform.envs.VecEnv``; ``VoxelActorCritic`` is the paper's network
over uint8 voxel grids, ``MLPActorCritic`` serves flat observations; the control env's controllers are in
``freeform.agents.networks.controllers`` (``CONTROLLERS``, ``build_controller``) and ``freeform.agents.controller_file``
(``save_controller`` / ``read_controller``).
"""

from freeform.agents.controller_file import read_controller, save_controller
from freeform.agents.distill import Distillation, DistillConfig
from freeform.agents.distill.teachers import TeacherBank
from freeform.agents.networks import GroupedMLPActorCritic, MLPActorCritic, VoxelActorCritic
from freeform.agents.networks.codesign_network import CodesignActorCritic
from freeform.agents.networks.controllers import (
    CONTROLLERS,
    ContextConvController,
    ConvController,
    MLPController,
    VoxelAttentionController,
    build_controller,
)
from freeform.agents.networks.recurrent import RecurrentActorCritic
from freeform.agents.ppo import PPO, PPOConfig

__all__ = ["CONTROLLERS", "PPO", "CodesignActorCritic", "ContextConvController", "ConvController", "MLPActorCritic",
           "MLPController", "PPOConfig", "VoxelActorCritic", "VoxelAttentionController", "build_controller",
           "read_controller", "save_controller"]
__all__ += ["DistillConfig", "Distillation", "GroupedMLPActorCritic", "RecurrentActorCritic", "TeacherBank"]
