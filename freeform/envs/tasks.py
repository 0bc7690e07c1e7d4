"""Tasks: what a finished design is scored by (one reward per final grid).

A task follows :class:`freeform.envs.base.Task`: ``reward(final_grids [N, ρ, ρ, ρ] uint8) -> [N] float32``. A task
may also accept a keyword ``bodies=`` (the grids' largest components, ``[N, ρ, ρ, ρ] uint8``); ``DesignEnv``
passes the bodies it has already computed to such tasks, so they are not labelled twice. A task with a ``stats``
mapping (:class:`freeform.envs.base.ReportsStats`, as ``LocomotionTask``) has its figures logged every epoch.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from freeform.body import check_grids, largest_component, serial_on_cpu

__all__ = ["ControlledLocomotionTask", "FrozenController", "LocomotionTask", "SimulatedTask", "VolumeTask"]


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
        with serial_on_cpu(bodies.device):
            return (bodies != 0).reshape(bodies.shape[0], -1).sum(dim=1).to(torch.float32)


ARCHS = ("auto", "cpu", "cuda")


class SimulatedTask:
    """What every task scored in simulation shares: the bodies (largest 6-connected components) of a batch are
    simulated by :mod:`freeform.sim` in one ``Simulator.simulate`` call; empty bodies are not simulated and score 0;
    a robot that fails (diverged, stopped by ``sim.step_cap``, or a non-finite score) scores 0 and is counted.
    A subclass says what it asks of the simulator (:meth:`simulate_options`) and how a result becomes rewards
    (:meth:`score`).

    ``placements`` k places each body at k yaw rotations about the vertical axis (1: as designed; 2: and turned
    half-way; 4: every quarter turn, counterclockwise seen from above), all simulated in the same batch (a batch
    gives every robot its solo result), and scores it at its best: placement is part of the experiment, as for a
    physical robot. It costs k simulated robots per body. After each call :attr:`yaw` holds each body's chosen
    placement in quarter turns ``[N]`` (0 for an empty body; the first best on ties).

    After each :meth:`reward` call, :attr:`stats` holds the call's figures as TensorBoard tags:
    ``perf/sim_seconds`` (wall time of the simulate call), ``perf/voxel_steps_per_second`` (simulated voxels ×
    steps / that time), ``stats/sim_diverged`` (robots that scored 0 by failing: diverged or stalled),
    ``stats/sim_stalled`` (stopped by ``sim.step_cap``) and ``stats/sim_bodies`` (bodies simulated).
    """

    def __init__(self, sim: Any = None, device: str | torch.device | None = None, arch: str = "auto",
                 simulator: Any = None, placements: int = 1) -> None:
        """
        Args:
            sim: a ``freeform.sim.SimConfig`` (default: the paper's materials and protocol, Voxelyze semantics).
            device: where the rewards are returned (default: the final grids' device).
            arch: backend of the simulator: "auto" (CUDA when present), "cpu" or "cuda".
            simulator: a ready ``freeform.sim.Simulator`` (overrides ``sim`` and ``arch``; tests use it).
            placements: yaw rotations each body is tried at, 1 | 2 | 4 (class docstring).
        """
        from freeform.sim import SimConfig, Simulator

        if placements not in PLACEMENTS:
            raise ValueError(f"placements must be one of {PLACEMENTS} (yaw rotations tried per body), got {placements!r}")
        self.placements = int(placements)
        self.yaw = torch.zeros(0, dtype=torch.int64)
        if simulator is None:
            if arch not in ARCHS:
                raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
            simulator = Simulator(sim if sim is not None else SimConfig(), arch=arch)
        self.simulator = simulator
        self.device = torch.device(device) if device is not None else None
        self.stats: dict[str, float] = {}

    @property
    def sim_config(self) -> Any:
        """The ``SimConfig`` the bodies are simulated with."""
        return self.simulator.config

    def simulate_options(self) -> dict[str, Any]:
        """Keyword arguments of ``Simulator.simulate`` beyond the bodies."""
        return {}

    def score(self, result: Any) -> torch.Tensor:
        """``SimResult`` of the ``B`` simulated bodies -> their rewards ``[B]`` (a non-finite one counts as failed)."""
        raise NotImplementedError

    def reward(self, final_grids: torch.Tensor, bodies: torch.Tensor | None = None) -> torch.Tensor:
        """``final_grids`` ``[N, ρ, ρ, ρ] uint8`` (``bodies`` optional: their largest components, same shape) ->
        rewards ``[N] float32``."""
        if bodies is None:
            check_grids(final_grids, name="final_grids")
            bodies = largest_component(final_grids)
        device = self.device if self.device is not None else final_grids.device
        volume = (bodies != 0).reshape(bodies.shape[0], -1).sum(dim=1)
        reward = torch.zeros(bodies.shape[0], dtype=torch.float32, device=device)
        self.yaw = torch.zeros(bodies.shape[0], dtype=torch.int64, device=device)
        live = torch.nonzero(volume > 0).flatten()
        k = self.placements
        self.stats = {"perf/sim_seconds": 0.0, "perf/voxel_steps_per_second": 0.0, "stats/sim_diverged": 0.0,
                      "stats/sim_stalled": 0.0, "stats/sim_bodies": float(k * live.numel())}
        if live.numel() == 0:  # nothing to simulate: every body is empty
            return reward
        turns = [q * (4 // k) for q in range(k)]  # quarter turns of each placement
        candidates = torch.cat([torch.rot90(bodies[live], q, dims=(1, 2)) for q in turns])  # [k·L, ...] placement-major
        t0 = time.perf_counter()
        result = self.simulator.simulate(candidates, **self.simulate_options())
        seconds = time.perf_counter() - t0
        score = self.score(result).to(device, torch.float32)
        failed = (result.diverged | result.stalled).to(device) | ~torch.isfinite(score)
        scores = torch.where(failed, 0.0, score).reshape(k, live.numel())
        best = scores.argmax(dim=0)  # the first best placement on ties (the design's own when all equal)
        reward[live.to(device)] = scores.gather(0, best[None]).squeeze(0)
        self.yaw[live.to(device)] = torch.tensor(turns, device=device)[best]
        volume_k = volume[live].cpu().to(torch.float64).repeat(k)
        voxel_steps = float((volume_k * result.steps.to(torch.float64)).sum())
        self.stats.update({"perf/sim_seconds": seconds,
                           "perf/voxel_steps_per_second": voxel_steps / max(seconds, 1e-12),
                           "stats/sim_diverged": float(failed.sum()),
                           "stats/sim_stalled": float(result.stalled.sum())})
        return reward


PLACEMENTS = (1, 2, 4)
"""The yaw placements a simulated task may try per body (``placements``): as designed, also turned half-way, or
every quarter turn."""

MEASURES = ("max_voxel", "com")
"""What :class:`LocomotionTask` rewards: the largest voxel displacement (the paper's) or the centre of mass's."""


class LocomotionTask(SimulatedTask):
    """The paper's locomotion task: the reward is how far the body moves in simulation (voxel lengths).

    The bodies are simulated with ``sim``'s protocol (paper: 5 s burn-in with actuation running, then a 5 s
    evaluation window; :class:`SimulatedTask` for what all simulated tasks share). The reward is the horizontal
    displacement across the window that ``measure`` names: ``"max_voxel"``, the maximum over voxels (the paper's),
    or ``"com"``, the centre of mass's; rewards below ``min_reward`` become 0 (spec design.md, "Rewards"). A body
    without muscle earns ≈ 0.
    """

    def __init__(self, sim: Any = None, device: str | torch.device | None = None, arch: str = "auto",
                 min_reward: float = 1e-3, simulator: Any = None, measure: str | None = None,
                 placements: int = 1) -> None:
        """``min_reward``: rewards below it become 0 (spec: 1e-3 voxel lengths); ``measure``: ``"max_voxel"`` |
        ``"com"`` (None: the deprecated ``sim.reward``, whose default is the paper's max_voxel); the rest as
        :class:`SimulatedTask`."""
        if not min_reward >= 0:
            raise ValueError(f"min_reward must be >= 0, got {min_reward}")
        if measure is not None and measure not in MEASURES:
            raise ValueError(f"measure must be one of {MEASURES}, got {measure!r}")
        super().__init__(sim=sim, device=device, arch=arch, simulator=simulator, placements=placements)
        self.min_reward = float(min_reward)
        if measure is None and self.sim_config.reward != "max_voxel":
            warnings.warn(f"sim.reward={self.sim_config.reward!r} is deprecated: the task chooses its measure "
                          f"(task.options.measure={self.sim_config.reward}, LocomotionTask(measure=...))",
                          DeprecationWarning, stacklevel=2)
        self.measure = measure if measure is not None else self.sim_config.reward

    def score(self, result: Any) -> torch.Tensor:
        chosen = result.max_voxel_displacement if self.measure == "max_voxel" else result.com_displacement
        displacement = chosen.to(torch.float32)
        return torch.where(displacement < self.min_reward, 0.0, displacement)  # NaN stays NaN: counted as failed


class FrozenController(Protocol):
    """A trained controller, read once by the layer that builds the task (``freeform.agents.controller_file.
    read_controller`` gives one): the episode it was trained under (``control``, a ``ControlConfig``), its physics
    (``sim``, a ``SimConfig``; None: the default), where it came from (``path``), and ``policy_for(bodies
    [M, ρ, ρ, ρ] uint8)``, the controller built for a box that holds those bodies acting by its mean command:
    ``policy.box``, ``policy(obs, state) -> (actions, state)`` (``state`` None at the episode's start) and
    ``policy.observe(state, reward) -> state`` after every step (a controller that reads rewards is told)."""

    control: Any
    sim: Any
    path: Any

    def policy_for(self, bodies: torch.Tensor) -> Any: ...


class ControlledLocomotionTask:
    """Locomotion under a trained controller: each body is driven for one control episode by ``controller`` (a
    :class:`FrozenController`: ``freeform.agents.controller_file.read_controller`` of a ``controller.pt``, a folder
    holding one, or a control run's directory), and its reward is how far it moves, in voxel lengths:
    the control env's return under ``headings`` (default "any": the distance moved in the plane, the locomotion
    score; "fixed": along +x). The episode is the controller's own (its ``ControlConfig``: settling, window,
    residual control, strokes, the muscles' bandwidth) in its own physics (its ``SimConfig``), and the controller
    acts by its mean command, deterministically: a design is scored by what the controller learnt, not by its
    exploration. So design RL on this task learns bodies for that controller — design after control, the
    controller frozen (``docs/codesign.md``).

    Empty bodies score 0 and are not simulated; a body that fails in simulation (diverged) scores what it moved up
    to then. ``stats`` as :class:`SimulatedTask`'s (``perf/sim_seconds``: the episode's wall time)."""

    def __init__(self, controller: FrozenController, sim: Any = None, device: str | torch.device | None = None,
                 arch: str = "cpu", headings: str = "any", seed: int = 0) -> None:
        """``sim``: the run's ``SimConfig``, checked to have the controller's materials (the physics is the
        controller's own); ``arch``: "cpu" | "cuda" | "auto"; ``seed``: the episodes' headings where they are
        drawn (``headings="random"``)."""
        from dataclasses import replace

        from freeform.envs.control import HEADINGS, ControlEnv
        from freeform.sim import SimConfig, Simulator

        if arch not in ARCHS:
            raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
        if headings not in HEADINGS:
            raise ValueError(f"headings must be one of {HEADINGS}, got {headings!r}")
        self.sim = controller.sim or SimConfig()
        if sim is not None and len(sim.materials) != len(self.sim.materials):
            raise ValueError(f"the controller {controller.path} was trained with {len(self.sim.materials)} materials "
                             f"and the run's sim has {len(sim.materials)}: design with the materials it knows")
        self.controller, self.source, self.seed = controller, controller.path, int(seed)
        self.control = replace(controller.control, headings=headings)
        self.control.validate()
        self.device = torch.device(device) if device is not None else None
        # one simulator for every call, its device arrays reused: the control env's physics (commanded actuation)
        self.simulator = Simulator(ControlEnv.simulation(self.sim, self.control), arch=arch)
        self.stats: dict[str, float] = {}

    def reward(self, final_grids: torch.Tensor, bodies: torch.Tensor | None = None) -> torch.Tensor:
        """``final_grids`` ``[N, ρ, ρ, ρ] uint8`` (``bodies`` optional: their largest components) -> each body's
        move under the controller ``[N] float32``."""
        from freeform.envs.control import ControlEnv

        if bodies is None:
            check_grids(final_grids, name="final_grids")
            bodies = largest_component(final_grids)
        device = self.device if self.device is not None else final_grids.device
        bodies = bodies.cpu()
        live = torch.nonzero(bodies.reshape(bodies.shape[0], -1).any(1)).flatten()
        reward = torch.zeros(bodies.shape[0], dtype=torch.float32)
        self.stats = {"perf/sim_seconds": 0.0, "stats/sim_bodies": float(live.numel())}
        if live.numel() == 0:
            return reward.to(device)
        t0 = time.perf_counter()
        policy = self.controller.policy_for(bodies[live])
        env = ControlEnv(bodies[live], sim=self.sim, control=self.control, seed=self.seed, box=tuple(policy.box),
                         simulator=self.simulator)
        obs, total, state = env.reset(), torch.zeros(len(live), dtype=torch.float64), None
        with torch.no_grad():
            for _ in range(self.control.steps):
                actions, state = policy(obs, state)
                obs, step_reward, _, _ = env.step(actions)
                state = policy.observe(state, step_reward)  # (a controller that reads rewards: a gate)
                total += step_reward.double()
        reward[live] = total.float()
        self.stats["perf/sim_seconds"] = time.perf_counter() - t0
        return reward.to(device)
