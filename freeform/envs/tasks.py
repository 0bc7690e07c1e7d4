"""Tasks: what a finished design is scored by (one reward per final grid).

A task follows :class:`freeform.envs.base.Task`: ``reward(final_grids [N, ρ, ρ, ρ] uint8) -> [N] float32``. A task
may also accept a keyword ``bodies=`` (the grids' largest components, ``[N, ρ, ρ, ρ] uint8``); ``DesignEnv``
passes the bodies it has already computed to such tasks, so they are not labelled twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from freeform.body import check_grids, largest_component

__all__ = ["VolumeTask"]


@dataclass
class VolumeTask:
    """The paper's volume task: the reward is the number of voxels in the body (the largest component).

    The paper uses it with k = 2 materials (empty, passive); any k works, every non-empty material counts.
    """

    def reward(self, final_grids: torch.Tensor, bodies: torch.Tensor | None = None) -> torch.Tensor:
        """``final_grids`` ``[N, ρ, ρ, ρ] uint8`` (``bodies`` optional, same shape) -> body volumes ``[N] float32``."""
        if bodies is None:
            check_grids(final_grids, name="final_grids")
            bodies = largest_component(final_grids)
        return (bodies != 0).reshape(bodies.shape[0], -1).sum(dim=1).to(torch.float32)
