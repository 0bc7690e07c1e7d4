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

import time
from collections.abc import Callable
from typing import Any

import torch

from freeform.body import check_grids, largest_component

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
@trajectory_reward("directional")
def directional(trace: Any) -> torch.Tensor:
    """+x progress of the centre of mass, minus its sideways drift |Δy| (voxel lengths)."""
    d = (final(trace, trace.com) - settled(trace, trace.com)) / trace.voxel_size
    return d[:, 0] - d[:, 1].abs()


@trajectory_reward("rough")
def rough(trace: Any) -> torch.Tensor:
    """Horizontal distance the centre of mass travels in any direction (voxel lengths); run on rough ground."""
    d = (final(trace, trace.com) - settled(trace, trace.com)) / trace.voxel_size
    return d[:, :2].norm(dim=1)


@trajectory_reward("climb")
def climb(trace: Any) -> torch.Tensor:
    """Net progress of the centre of mass towards +x (uphill on ``Terrain.slope(degrees, "x")``), voxel lengths."""
    return (final(trace, trace.com) - settled(trace, trace.com))[:, 0] / trace.voxel_size


@trajectory_reward("stairs")
def stairs(trace: Any) -> torch.Tensor:
    """Net progress of the centre of mass towards +x, up ``Terrain.steps`` (voxel lengths)."""
    return (final(trace, trace.com) - settled(trace, trace.com))[:, 0] / trace.voxel_size


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
class TrajectoryTask:
    """Reward = ``reward_fn(trace)`` of each body's simulated trajectory (``freeform.sim.Trace``).

    Like ``LocomotionTask``, the bodies (largest components) of a batch are simulated in one call, empty bodies
    are not simulated, and failures (diverged or stalled) score 0; ``stats`` holds the call's figures
    (``perf/sim_seconds``, ``perf/voxel_steps_per_second``, ``stats/sim_diverged``, ``stats/sim_stalled``,
    ``stats/sim_bodies``).
    """

    def __init__(self, reward_fn: RewardFn | str, sim: Any = None, trace_every: float = 0.02,
                 device: str | torch.device | None = None, arch: str = "auto", simulator: Any = None) -> None:
        """
        Args:
            reward_fn: ``(trace) -> [B]`` rewards (torch), or a name in ``TRAJECTORY_REWARDS``.
            sim: a ``freeform.sim.SimConfig`` (its ``terrain`` is the ground; default: flat, the paper's protocol).
            trace_every: seconds between trace samples.
            device: where rewards are returned (default: the final grids' device).
            arch: Taichi backend ("auto" | "cpu" | "cuda"). simulator: a ready ``Simulator`` (overrides both).
        """
        from freeform.sim import SimConfig, Simulator

        if isinstance(reward_fn, str):
            if reward_fn not in TRAJECTORY_REWARDS:
                raise ValueError(f"reward_fn must be one of {sorted(TRAJECTORY_REWARDS)}, got {reward_fn!r}")
            reward_fn = TRAJECTORY_REWARDS[reward_fn]
        if not trace_every > 0:
            raise ValueError(f"trace_every must be > 0 seconds, got {trace_every}")
        if simulator is None:
            if arch not in ("auto", "cpu", "cuda"):
                raise ValueError(f"arch must be one of ('auto', 'cpu', 'cuda'), got {arch!r}")
            simulator = Simulator(sim if sim is not None else SimConfig(), arch=arch)
        self.reward_fn = reward_fn
        self.simulator = simulator
        self.trace_every = float(trace_every)
        self.device = torch.device(device) if device is not None else None
        self.stats: dict[str, float] = {}
        self.last_trace: Any = None

    @property
    def sim_config(self) -> Any:
        return self.simulator.config

    def reward(self, final_grids: torch.Tensor, bodies: torch.Tensor | None = None) -> torch.Tensor:
        """``final_grids`` ``[N, ρ, ρ, ρ] uint8`` (``bodies``: their largest components) -> rewards ``[N] float32``."""
        if bodies is None:
            check_grids(final_grids, name="final_grids")
            bodies = largest_component(final_grids)
        device = self.device if self.device is not None else final_grids.device
        volume = (bodies != 0).reshape(bodies.shape[0], -1).sum(dim=1)
        reward = torch.zeros(bodies.shape[0], dtype=torch.float32, device=device)
        live = torch.nonzero(volume > 0).flatten()
        self.stats = {"perf/sim_seconds": 0.0, "perf/voxel_steps_per_second": 0.0, "stats/sim_diverged": 0.0,
                      "stats/sim_stalled": 0.0, "stats/sim_bodies": float(live.numel())}
        if live.numel() == 0:
            return reward
        t0 = time.perf_counter()
        result = self.simulator.simulate(bodies[live], trace_every=self.trace_every)
        seconds = time.perf_counter() - t0
        self.last_trace = result.trace
        r = self.reward_fn(result.trace).to(device, torch.float32)
        failed = (result.diverged | result.stalled).to(device) | ~torch.isfinite(r)
        reward[live.to(device)] = torch.where(failed, 0.0, r)
        voxel_steps = float((volume[live].cpu().to(torch.float64) * result.steps.to(torch.float64)).sum())
        self.stats.update({"perf/sim_seconds": seconds,
                           "perf/voxel_steps_per_second": voxel_steps / max(seconds, 1e-12),
                           "stats/sim_diverged": float(failed.sum()),
                           "stats/sim_stalled": float(result.stalled.sum())})
        return reward
