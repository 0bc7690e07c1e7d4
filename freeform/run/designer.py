"""A design run's last policy as a :class:`freeform.envs.untrained.Designer`: the bodies it builds, for a control
stream over them (``control.designer``; ``freeform.envs.population``). It lives with the run, which joins the
agents' PPO to the design env: the envs never import the agents."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from freeform.agents import PPO
from freeform.body import largest_component, serial_on_cpu
from freeform.checkpoint import load_checkpoint
from freeform.config import from_container
from freeform.envs.design import DesignEnv
from freeform.envs.untrained import DesignBodies


@dataclass(frozen=True)
class TrainedDesigner:
    """The design run at ``source`` (its directory or a checkpoint) as a ``Designer``:
    ``TrainedDesigner(source)(n, sizes, seed)`` is :func:`trained_design_bodies`."""

    source: str

    def __call__(self, n: int, sizes: DesignBodies, seed: int) -> torch.Tensor:
        return trained_design_bodies(self.source, n, sizes, seed)


@functools.lru_cache(maxsize=4)
def _designer(path: str) -> tuple[Any, Any, Any]:
    """The design run's last PPO (on a design env of its own sizes, no task), that env and its config (the run's
    ``env`` section), read once."""
    payload = load_checkpoint(path)
    if "config" not in payload:
        raise ValueError(f"control.designer={path}: not a run's checkpoint (no run config)")
    cfg = from_container(payload["config"])
    if cfg.control is not None:
        raise ValueError(f"control.designer={path}: a control run's checkpoint; the designer is a design run "
                         "(a run without a control section), whose policy builds bodies")
    e = cfg.env
    env = DesignEnv(e.num_envs, e, materials=cfg.task.materials, compute_metrics=False)
    with torch.random.fork_rng(devices=[]):  # (building the network draws: the caller's stream stays as it was)
        ppo = PPO.load(path, env, device="cpu")
    return ppo, env, e


@torch.no_grad()
def trained_design_bodies(designer: str, n: int, sizes: DesignBodies, seed: int) -> torch.Tensor:
    """``n`` bodies a trained design policy builds, uint8 ``[n, ρ, ρ, ρ]`` (each design's largest component):
    ``designer`` a design run's directory (its ``checkpoints/last.pt``) or a checkpoint, its actions sampled as in
    training from a generator seeded ``seed``, so the bodies are a function of ``(designer, n, seed)``. The run's
    design sizes must be ``sizes``' (the stream's box is built from them)."""
    path = Path(designer)
    path = path / "checkpoints" / "last.pt" if path.is_dir() else path
    if not path.is_file():
        raise ValueError(f"control.designer={designer!r}: no such checkpoint ({path} is not a file)")
    ppo, env, e = _designer(str(path.resolve()))
    theirs = (env.resolution, env.materials, env.steps, env.bundle_size)
    ours = (sizes.resolution, sizes.materials, sizes.steps, sizes.bundle_size)
    if theirs != ours:
        raise ValueError(f"control.designer={designer!r} designs on a {theirs[0]}^3 grid with {theirs[1]} materials "
                         f"and {theirs[2]} steps of {theirs[3]}^3 bundles, and this run's design sizes (env.resolution, "
                         f"task.materials, env.steps, env.bundle_size) are {ours}: give the run the designer's sizes")
    sampler = DesignEnv(n, e, materials=env.materials, compute_metrics=False)
    ppo.generator.manual_seed(seed)
    grids = torch.zeros((n, *sampler.observation_shape), dtype=torch.uint8)
    for _ in range(env.steps):  # (the design env's steps, without its scoring)
        actions = ppo.act(grids).cpu()
        with serial_on_cpu("cpu"):
            grids = sampler.place_bundles(grids, actions)
    return largest_component(grids)


__all__ = ["TrainedDesigner", "trained_design_bodies"]
