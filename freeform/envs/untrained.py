"""Bodies an untrained design policy builds — what a control run, a population stream, the benchmarks and the
evolutionary baselines start from — and the walker among them.

:class:`DesignBodies` holds the design env's sizes; :func:`untrained_design_bodies` the largest components of the
grids a ``DesignEnv`` of those sizes builds from actions drawn from N(0, I); :func:`untrained_walker` the one of
them whose open-loop gait goes furthest. A trained design policy's bodies come from a :class:`Designer`, which the
layer that builds both the policy and the env passes in (``freeform.run.designer``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from freeform.body import largest_component, serial_on_cpu
from freeform.envs.control import ControlConfig, open_loop_displacement
from freeform.envs.design import DesignEnv, EnvConfig
from freeform.sim import SimConfig


class Designer(Protocol):
    """A trained design policy that builds bodies: ``designer(n, sizes, seed) -> uint8 [n, ρ, ρ, ρ]`` (each
    design's largest component, a function of ``(n, seed)``); ``source`` names it (a run's checkpoint path) in an
    env's saved config."""

    source: str

    def __call__(self, n: int, sizes: DesignBodies, seed: int) -> torch.Tensor: ...


@dataclass(frozen=True)
class DesignBodies:
    """The design env's sizes, for bodies an untrained design policy builds (:func:`untrained_design_bodies`): grid
    ``resolution`` ρ, ``materials`` k (with empty: 4 = empty, passive and two muscles in anti-phase), ``steps``
    design actions of ``bundle_size``³ bundles (locomotion_cpu's by default). ``designer``: a trained design
    policy that builds the bodies instead (its sizes must be these)."""

    resolution: int = 8
    materials: int = 4
    steps: int = 20
    bundle_size: int = 2
    designer: Designer | None = None

    def config(self) -> dict[str, object]:
        """The sizes as plain data (what an env's saved state is checked against): the designer by its source."""
        return {"resolution": self.resolution, "materials": self.materials, "steps": self.steps,
                "bundle_size": self.bundle_size, "designer": self.designer.source if self.designer else None}


def design_grids(env: DesignEnv, actions: torch.Tensor) -> torch.Tensor:
    """The final grids ``[N, ρ, ρ, ρ] uint8`` that ``actions [N, T, A]`` design in ``env`` (no task, no cost)."""
    actions = actions.to(env.device, torch.float32)
    grids = torch.zeros((actions.shape[0], *env.observation_shape), dtype=torch.uint8, device=env.device)
    with serial_on_cpu(env.device):
        for t in range(actions.shape[1]):
            grids = env.place_bundles(grids, actions[:, t])
    return grids


def untrained_design_grids(env: DesignEnv, seed: int) -> torch.Tensor:
    """The final grids ``[N, ρ, ρ, ρ] uint8`` of an untrained policy in ``env``: a ~ N(0, I) at each of its steps,
    drawn step by step (``[N, A]`` at a time) from a generator seeded ``seed``."""
    generator = torch.Generator().manual_seed(seed)
    actions = [torch.randn(env.num_envs, env.action_dim, generator=generator) for _ in range(env.steps)]
    return design_grids(env, torch.stack(actions, dim=1))


def untrained_design_bodies(n: int, resolution: int, materials: int, steps: int, bundle_size: int,
                            seed: int = 0) -> torch.Tensor:
    """Bodies of an untrained policy: uint8 ``[n, ρ, ρ, ρ]``, the largest 6-connected component of each grid that a
    ``DesignEnv`` of these sizes builds from ``steps`` actions drawn from N(0, I) (benchmarks, scripts, demos)."""
    env = DesignEnv(n, EnvConfig(resolution=resolution, steps=steps, bundle_size=bundle_size),
                    materials=materials, seed=seed, compute_metrics=False)
    return largest_component(untrained_design_grids(env, seed))


def untrained_walker(candidates: int, sizes: DesignBodies, seed: int = 0, sim: SimConfig | None = None,
                     control: ControlConfig | None = None, arch: str = "cpu") -> tuple[torch.Tensor, np.ndarray]:
    """The walker: of ``candidates`` bodies an untrained design policy builds with these ``sizes``
    (:func:`untrained_design_bodies`; the rare empty one dropped), the one whose open-loop gait goes furthest along
    +x in a control episode's window (``freeform.envs.control.open_loop_displacement``). Returns it
    ``[1, ρ, ρ, ρ]`` and every kept candidate's score."""
    grids = untrained_design_bodies(candidates, sizes.resolution, sizes.materials, sizes.steps, sizes.bundle_size,
                                    seed)
    grids = grids[(grids.flatten(1) > 0).any(dim=1)]
    scores = open_loop_displacement(grids, sim, control, arch)
    return grids[int(np.argmax(scores))][None], scores


__all__ = ["DesignBodies", "Designer", "design_grids", "untrained_design_bodies", "untrained_design_grids",
           "untrained_walker"]
