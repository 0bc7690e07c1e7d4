"""Agents: a hand-written batched PPO and its actor-critic networks.

``PPO(env, policy, PPOConfig(...))`` trains any ``freeform.envs.VecEnv``; ``VoxelActorCritic`` is the paper's network
over uint8 voxel grids, ``MLPActorCritic`` serves flat observations.
"""

from freeform.agents.networks import (
    CodesignActorCritic,
    ConvController,
    MLPActorCritic,
    MLPController,
    VoxelActorCritic,
)
from freeform.agents.observation_groups import GroupedMLPActorCritic
from freeform.agents.ppo import PPO, PPOConfig
from freeform.agents.recurrent import RecurrentActorCritic

__all__ = ["PPO", "CodesignActorCritic", "ConvController", "MLPActorCritic", "MLPController", "PPOConfig", "VoxelActorCritic"]
__all__ += ["GroupedMLPActorCritic", "RecurrentActorCritic"]
