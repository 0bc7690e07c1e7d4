"""Tasks written as a reward over the simulated trajectory: ``TrajectoryTask(reward_fn)``.

The bodies of a batch are simulated together (``Simulator.simulate(..., trace_every=...)``) and ``reward_fn`` maps
their ``freeform.sim.Trace`` (torch, batched: ``[B, F]`` samples of the centre of mass, lowest/highest voxel, box,
contacts, orientation) to one reward per body ``[B]``. A diverged or stalled robot and an empty body score 0.
``docs/tasks.md`` shows how to write one in a few lines.

Built-in rewards, registered by name (``task.name=<name>`` on the command line; ``TRAJECTORY_REWARDS``), all in
voxel lengths, from the settled state (the last sample of the burn-in) to the end of the evaluation window:

| name | reward |
|---|---|
| ``directional`` | +x progress of the COM minus its sideways drift \\|Δy\\| |
| ``rough`` | horizontal COM distance (any direction), meant for rough ground |
| ``climb`` | net progress of the COM towards +x, uphill on ``Terrain.slope`` |
| ``stairs`` | net progress of the COM towards +x, up ``Terrain.steps`` |
| ``jump`` | peak rise of the COM above its settled height during the evaluation window |
| ``tallest`` | the body's standing height at the end (highest voxel top above the floor), a structural task |
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from freeform.envs.tasks import SimulatedTask

__all__ = ["TRAJECTORY_REWARDS", "TrajectoryTask", "final", "settled", "trajectory_reward"]

RewardFn = Callable[[Any], torch.Tensor]
TRAJECTORY_REWARDS: dict[str, RewardFn] = {}
"""name -> reward function ``(trace) -> [B]``; ``task.name=<name>`` builds a ``TrajectoryTask`` of it."""


def trajectory_reward(name: str) -> Callable[[RewardFn], RewardFn]:
    """Decorator: register ``fn(trace) -> [B]`` as the trajectory task ``name``."""

    def decorate(fn: RewardFn) -> RewardFn:
        TRAJECTORY_REWARDS[name] = fn
        return fn

    return decorate


def _at(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x`` ``[B, F, ...]`` at sample ``index[b]`` of each body -> ``[B, ...]``."""
    idx = index.view(-1, 1, *([1] * (x.dim() - 2))).expand(-1, 1, *x.shape[2:])
    return x.gather(1, idx).squeeze(1)


def settled(trace: Any, x: torch.Tensor) -> torch.Tensor:
    """``x`` ``[B, F, ...]`` at each robot's last sample of the burn-in (its settled state)."""
    return _at(x, trace.burn_in_end)


def final(trace: Any, x: torch.Tensor) -> torch.Tensor:
    """``x`` ``[B, F, ...]`` at each robot's last valid sample (the end of its evaluation window)."""
    return _at(x, (trace.valid.sum(dim=1) - 1).clamp_min(0))


# ------------------------------------------------------------------------------------------------ built-in rewards
def forward_progress(trace: Any) -> torch.Tensor:
    """``[B]`` the centre of mass's +x progress from its settled state to the end, or 0 when it went back (voxel
    lengths). Why not the net progress: a random body's is as often negative as positive (on a slope most slide
    down), and a design policy cuts that tail most easily by designing bodies that do not move at all, a local
    optimum it then stays in (docs/tasks.md, "Why forward progress"); scoring going back as standing still leaves
    moving worth exploring."""
    return ((final(trace, trace.com) - settled(trace, trace.com))[:, 0] / trace.voxel_size).clamp_min(0.0)


@trajectory_reward("directional")
def directional(trace: Any) -> torch.Tensor:
    """+x progress of the centre of mass, minus its sideways drift |Δy|; 0 when that is negative (voxel lengths)."""
    d = (final(trace, trace.com) - settled(trace, trace.com)) / trace.voxel_size
    return (d[:, 0] - d[:, 1].abs()).clamp_min(0.0)


@trajectory_reward("rough")
def rough(trace: Any) -> torch.Tensor:
    """Horizontal distance the centre of mass travels in any direction (voxel lengths); run on rough ground."""
    d = (final(trace, trace.com) - settled(trace, trace.com)) / trace.voxel_size
    return d[:, :2].norm(dim=1)


@trajectory_reward("climb")
def climb(trace: Any) -> torch.Tensor:
    """Progress of the centre of mass towards +x, uphill on ``Terrain.slope(degrees, "x")``; a body that slides or
    walks back scores 0, as one that stands (voxel lengths)."""
    return forward_progress(trace)


@trajectory_reward("stairs")
def stairs(trace: Any) -> torch.Tensor:
    """Progress of the centre of mass towards +x, up ``Terrain.steps``; 0 for going back (voxel lengths)."""
    return forward_progress(trace)


@trajectory_reward("jump")
def jump(trace: Any) -> torch.Tensor:
    """Peak rise of the centre of mass above its settled height during the evaluation window (voxel lengths)."""
    rise = trace.com[..., 2] - settled(trace, trace.com)[:, 2:3]
    rise = torch.where(trace.evaluation, rise, torch.zeros_like(rise))
    return rise.max(dim=1).values.clamp_min(0.0) / trace.voxel_size


@trajectory_reward("tallest")
def tallest(trace: Any) -> torch.Tensor:
    """Standing height at the end: the highest voxel's top above the flat floor (voxel lengths). A body that sags
    or topples while it settles loses what it lost in height."""
    return final(trace, trace.z_max) / trace.voxel_size + 1.0


# ------------------------------------------------------------------------------------------------ the task
class TrajectoryTask(SimulatedTask):
    """Reward = ``reward_fn(trace)`` of each body's simulated trajectory (``freeform.sim.Trace``).

    What all simulated tasks share (one batched simulate call, empty bodies unsimulated, failures scoring 0,
    ``stats``) is :class:`freeform.envs.tasks.SimulatedTask`; ``last_trace`` keeps the last call's trace.
    """

    def __init__(self, reward_fn: RewardFn | str, sim: Any = None, trace_every: float = 0.02,
                 device: str | torch.device | None = None, arch: str = "auto", simulator: Any = None,
                 placements: int = 1) -> None:
        """
        Args:
            reward_fn: ``(trace) -> [B]`` rewards (torch), or a name in ``TRAJECTORY_REWARDS``.
            sim: a ``freeform.sim.SimConfig`` (its ``terrain`` is the ground; default: flat, the paper's protocol).
            trace_every: seconds between trace samples.
            device, arch, simulator, placements: as :class:`freeform.envs.tasks.SimulatedTask`.
        """
        if isinstance(reward_fn, str):
            if reward_fn not in TRAJECTORY_REWARDS:
                raise ValueError(f"reward_fn must be one of {sorted(TRAJECTORY_REWARDS)}, got {reward_fn!r}")
            reward_fn = TRAJECTORY_REWARDS[reward_fn]
        if not trace_every > 0:
            raise ValueError(f"trace_every must be > 0 seconds, got {trace_every}")
        super().__init__(sim=sim, device=device, arch=arch, simulator=simulator, placements=placements)
        self.reward_fn = reward_fn
        self.trace_every = float(trace_every)
        self.last_trace: Any = None

    def simulate_options(self) -> dict[str, Any]:
        return {"trace_every": self.trace_every}

    def score(self, result: Any) -> torch.Tensor:
        self.last_trace = result.trace
        return self.reward_fn(result.trace)
