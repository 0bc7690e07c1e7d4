"""A controller averaged over the ground's symmetries (test-time augmentation): what it commands a body is the mean,
over the group's elements g, of its commands to the body turned by g, turned back.

Where the task is unchanged by the group (steering along a heading that turns with the body, in the world's frame;
``freeform.envs.symmetry``) the best controller commands a turned body its commands turned, and the average is the
projection of any controller onto such equivariant ones: exactly equivariant whatever it averages, equal to the
controller where that already was. A distillation with ``algo.symmetry`` teaches the student the same thing from
turned samples; this imposes it when acting, at ``size`` forward passes a step. Under ``headings="any"`` the wave
head's wave runs along x whatever the turn, so only the ``mirror`` group keeps a wave-head controller's gait.

    python -m experiments.control --evaluate RUN --bodies BODIES.npy --headings random --symmetrize ground ...
"""

from __future__ import annotations

from typing import Any, Protocol

import torch
from torch import nn

from freeform.agents.recurrent import RecurrentPolicy


class TurnsCells(Protocol):
    """A group acting on a control env's observations and per-cell values (``freeform.envs.symmetry
    .PlanarSymmetry``): ``size`` elements, element 0 the identity, ``inverse(g)`` the element undoing ``g``."""

    size: int

    def inverse(self, g: int) -> int: ...

    def observations(self, obs: torch.Tensor, g: torch.Tensor) -> torch.Tensor: ...

    def cells(self, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor: ...


class GroupAveraged(nn.Module):
    """``controller`` (a feed-forward controller: ``obs [N, C, Bx, By, Bz]`` → (mean, log σ, mask, value)) averaged
    over ``symmetry``'s elements: the mean and log σ ``[N, A]`` are the means of the turned bodies' ones turned back,
    the mask the body's own, the value the mean of the turned bodies' values. One forward of ``size · N`` samples."""

    def __init__(self, controller: nn.Module, symmetry: TurnsCells) -> None:
        super().__init__()
        if isinstance(controller, RecurrentPolicy):
            raise ValueError(f"a group average needs a feed-forward controller; {type(controller).__name__} carries "
                             "a state through the episode (each turned copy would need its own)")
        self.controller, self.symmetry = controller, symmetry
        self.distribution: Any = getattr(controller, "distribution", None)
        self.register_buffer("inverse", torch.tensor([symmetry.inverse(g) for g in range(symmetry.size)]),
                             persistent=False)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        n, size = obs.shape[0], self.symmetry.size
        g = torch.arange(size, device=obs.device).repeat_interleave(n)  # [size·N]: block g is every body turned by g
        turned = self.symmetry.observations(obs.repeat(size, *(1,) * (obs.dim() - 1)), g)
        mean, log_std, mask, value = self.controller(turned)[:4]
        back = self.inverse[g]

        def average(x: torch.Tensor) -> torch.Tensor:  # per-cell values, each block turned back, then averaged
            return self.symmetry.cells(x, back).view(size, n, -1).mean(0)

        return average(mean), average(log_std), mask[:n], value.view(size, n).mean(0)


__all__ = ["GroupAveraged"]
