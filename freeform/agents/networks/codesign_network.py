"""The co-design actor-critic: the paper's design network while designing, a controller while controlling, one
policy over a ``freeform.envs.CodesignEnv``'s episodes. It builds on the networks and the controllers, which know
nothing of it."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.networks import VoxelActorCritic, rebuild
from freeform.agents.networks.controller_heads import DEFAULT_WAVE, HandSetWave
from freeform.agents.networks.controllers import CODESIGN_KINDS, CONTROLLERS, ConvController, build_controller
from freeform.distributions import MaskedDiagGaussian


@dataclass(frozen=True)
class CodesignObservation:
    """A co-design observation's layout ``[N, C, ρ, ρ, ρ]``: the grid's ``resolution`` ρ, the ``stage_channel`` (0
    while designing, 1 while controlling), the ``grid_channel`` (the grid's material indices), the control env's
    channels ``control_channels = (start, stop)``, and their ``mask_channel`` / ``filled_channel``, counted from
    ``start``. A ``CodesignActorCritic``'s ``init_kwargs`` hold them by these names."""

    resolution: int
    stage_channel: int
    grid_channel: int
    control_channels: Any
    mask_channel: int
    filled_channel: int = 0


class CodesignActorCritic(nn.Module):
    """One actor-critic for a design-then-control episode (``freeform.envs.CodesignEnv``): the paper's design
    network (:class:`VoxelActorCritic`) on the grid channel while designing, a controller on the control channels
    while controlling (a :class:`ConvController` by default; any feed-forward kind of
    ``freeform.agents.networks.controllers.CONTROLLERS`` with its head, e.g. a population controller's context trunk and
    wave head); the stage channel chooses, per sample, which head acts and which value counts.

    Observations ``[N, C, ρ, ρ, ρ]`` laid out as ``observation`` (:class:`CodesignObservation`). Outputs a ``MaskedDiagGaussian``'s parameters
    over ``[3 + k design numbers, c·ρ³ control numbers]`` (c = 2 for a stroke head) and the value: (mean, log_std,
    mask, value); the mask is the design part while designing, the actuated cells while controlling.

    controller, controller_kwargs: the controller's registry kind and ``init_kwargs`` (None: a ``ConvController``
    ``controller_hidden`` wide, log σ ``log_std``, as before they could be chosen).
    """

    def __init__(self, observation: CodesignObservation, materials: int, hidden: int = 64,
                 controller_hidden: int = 16, log_std: float = -0.5, controller: str = "conv",
                 controller_kwargs: dict[str, Any] | None = None, trunk: str = "auto") -> None:
        super().__init__()
        o = observation
        resolution, stage_channel, grid_channel = o.resolution, o.stage_channel, o.grid_channel
        mask_channel, filled_channel = o.mask_channel, o.filled_channel
        start, stop = (int(c) for c in o.control_channels)
        self.init_kwargs = dict(resolution=resolution, materials=materials, stage_channel=stage_channel,
                                grid_channel=grid_channel, control_channels=(start, stop), mask_channel=mask_channel,
                                filled_channel=filled_channel, hidden=hidden, controller_hidden=controller_hidden,
                                log_std=log_std)
        if trunk != "auto":  # (a file from before the key rebuilds as it was)
            self.init_kwargs["trunk"] = trunk
        self.design = VoxelActorCritic(resolution, materials, hidden, trunk=trunk)
        if controller_kwargs is None:
            if controller != "conv":
                raise ValueError(f"controller {controller!r} needs its controller_kwargs (init_kwargs)")
            self.controller = ConvController(stop - start, (resolution,) * 3, mask_channel, filled_channel,
                                             controller_hidden, log_std)
        else:
            if controller not in CODESIGN_KINDS:
                raise ValueError(f"a co-design controller is one of {list(CODESIGN_KINDS)} (feed-forward, one set "
                                 f"of weights for every cell), got {controller!r}: set control.controller")
            self.controller = rebuild(CONTROLLERS[controller], controller_kwargs)
            self.init_kwargs.update(controller=controller, controller_kwargs=dict(controller_kwargs))
        if tuple(self.controller.box) != (resolution,) * 3:
            raise ValueError(f"the controller's box {tuple(self.controller.box)} is not the design grid's "
                             f"{(resolution,) * 3}")
        self.stage_channel, self.grid_channel, self.control_channels = stage_channel, grid_channel, (start, stop)
        self.design_dim = 3 + materials
        self.distribution = MaskedDiagGaussian(self.design_dim + self.controller.distribution.dim)

    @classmethod
    def for_env(cls, env: Any, hidden: int = 64, controller_hidden: int = 16, log_std: float = -0.5,
                controller: str = "conv", head: str = "direct", wave: HandSetWave = DEFAULT_WAVE,
                trunk: str = "auto") -> CodesignActorCritic:
        """The actor-critic for a ``CodesignEnv`` (its grid, materials and channels): a ``controller`` of that kind
        with that ``head`` (``freeform.agents.build_controller`` on the env's control stage; the default conv
        controller with the direct head is built as it always was), the design network's ``trunk``."""
        kwargs = None
        if (controller, head) != ("conv", "direct"):
            kwargs = dict(build_controller(controller, env.control_view(), controller_hidden, log_std, head,
                                           wave).init_kwargs)
        observation = CodesignObservation(env.rho, env.stage_channel, env.grid_channel, env.control_channels,
                                          env.mask_channel, env.filled_channel)
        return cls(observation, env.materials, hidden, controller_hidden, log_std, controller, kwargs, trunk)

    @classmethod
    def from_init_kwargs(cls, init_kwargs: dict[str, Any]) -> CodesignActorCritic:
        """Rebuilt from its (flat) ``init_kwargs`` (``freeform.agents.networks.rebuild``)."""
        names = {f.name for f in fields(CodesignObservation)}
        observation = CodesignObservation(**{k: v for k, v in init_kwargs.items() if k in names})
        return cls(observation, **{k: v for k, v in init_kwargs.items() if k not in names})

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, C, ρ, ρ, ρ]`` → (mean, log_std, mask ``[N, 3 + k + c·ρ³]``, value ``[N]``)."""
        controlling = obs[:, self.stage_channel, 0, 0, 0] > 0.5
        grids = obs[:, self.grid_channel].round().to(torch.uint8)
        mean_d, log_std_d, value_d = self.design(grids)
        start, stop = self.control_channels
        mean_c, log_std_c, mask_c, value_c = self.controller(obs[:, start:stop])
        designing = (~controlling).to(mean_d.dtype)[:, None]
        mask = torch.cat([designing.expand_as(mean_d), mask_c * (1.0 - designing)], dim=1)
        return (torch.cat([mean_d, mean_c], dim=1), torch.cat([log_std_d, log_std_c], dim=1), mask,
                torch.where(controlling, value_c, value_d))


__all__ = ["CodesignActorCritic", "CodesignObservation"]
