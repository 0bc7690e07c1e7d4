"""The networks: the paper's voxel actor-critic and the MLPs (``base``), the body controllers and their heads
(``controllers``, ``controller_heads``, ``attention_controllers``, ``codesign_network``), the recurrent cores
(``recurrent``), the design trunks (``fast_trunk``, ``gather_trunk``), observation groups and group averages. This
package's own names are ``base``'s, so that importing it builds no controller."""

from freeform.agents.networks.base import (
    TRUNK_IMPLEMENTATIONS,
    ActorCritic,
    DeclaresDistribution,
    GroupedActions,
    GroupedMLPActorCritic,
    MLPActorCritic,
    Rebuildable,
    SplitActorCritic,
    VoxelActorCritic,
    rebuild,
    resolve_trunk,
)

__all__ = ["ActorCritic", "DeclaresDistribution", "GroupedActions", "GroupedMLPActorCritic", "MLPActorCritic",
           "Rebuildable", "SplitActorCritic", "TRUNK_IMPLEMENTATIONS", "VoxelActorCritic", "rebuild", "resolve_trunk"]
