"""A controller averaged over the ground's symmetries (test-time augmentation): what it commands a body is the mean,
over the group's elements g, of its commands to the body turned by g, turned back.

Where the task is unchanged by the group (steering along a heading that turns with the body, in the world's frame;
``freeform.envs.symmetry``) the best controller commands a turned body its commands turned, and the average is the
projection of any controller onto such equivariant ones: exactly equivariant whatever it averages, equal to the
controller where that already was. A distillation with ``algo.symmetry`` teaches the student the same thing from
turned samples; this imposes it when acting, one forward pass over ``size`` · N samples a step. Under
``headings="any"`` the wave head's wave runs along x whatever the turn, so only the ``mirror`` group keeps a wave-head
controller's gait.

    python -m lab.control --evaluate RUN --bodies BODIES.npy --headings random --symmetrize ground ...
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import torch
from torch import nn

from freeform.agents.networks.controllers import CONTROLLERS
from freeform.agents.networks.recurrent import RecurrentPolicy


def check_turnable(key: str, group: str, headings: str, frame: str, controllers: Mapping[str, str]) -> None:
    """Refuses a group of turns (``key``: the option that asked for it) where turning a body changes its task or its
    controller: a turned body walks the turned way, which a fixed heading (+x) does not reward, nor the heading's
    frame (its task is +x, the heading no channel that turns along) — there only the mirror y → −y keeps the task;
    and a turned body sits elsewhere in its padded box (a flip reverses the whole box), which only a controller that
    the padding does not change sees as the same body (``controllers``: who → kind, each checked)."""
    if headings == "fixed" and group != "mirror":
        raise ValueError(f"{key}={group} turns the way a body walks, and control.headings=fixed rewards +x alone: use "
                         f"{key}=mirror (y -> -y keeps +x), or headings any or random")
    if frame == "heading" and headings != "any" and group != "mirror":
        raise ValueError(f"{key}={group} turns the way a body walks, and in control.frame=heading every task is +x of "
                         f"the heading's frame: use {key}=mirror (y -> -y keeps +x)")
    for who, kind in controllers.items():
        if not CONTROLLERS[kind].padding_invariant:
            raise ValueError(f"{key}={group} turns each body within its padded box, which only a controller that the "
                             f"padding does not change sees as the same body; {who} is {kind!r} (use "
                             f"{[k for k, c in CONTROLLERS.items() if c.padding_invariant]}, or no symmetry)")


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


__all__ = ["GroupAveraged", "check_turnable"]
