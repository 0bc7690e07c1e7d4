"""Closed-loop control of voxel bodies: a batched environment in which a controller sets every voxel's actuation
each control period, sensing the body on its own grid (issue 29's first environment; ``docs/physics.md``,
"Commanded actuation").

One episode: the bodies are placed and settle for ``burn_in`` seconds with zero commands (the controller does not
act then: every episode starts from a body at rest on the ground; under ``residual`` control the burn-in runs the
open-loop gait, so the controller takes over a body already walking), then ``steps`` control steps of ``period``
simulated seconds each. A step writes the actions as commands (T = T_base + A·a, so a ∈ [−1, 1] spans the
open-loop sine's range; a passive voxel's or an empty cell's entry has no effect), runs each robot until its own
clock passes the next control time (rl4design's dt differs per robot) and senses, all in one call to the device
(``Engine.control_step``). Every episode ends together, by its time limit (``truncated``), and the env resets itself. A robot
that diverges or stalls stays in the batch, frozen, with reward 0 until the episode ends.

Reward: the centre of mass's displacement along the robot's heading during the step, in voxel lengths; the
heading is +x (``headings="fixed"``, locomotion) or drawn uniformly per robot and episode (``"random"``, steering),
and is in the observation. ``headings="any"``: no heading — the step's growth of the centre of mass's distance
from where the episode started, in the ground plane (the return is that distance: the paper's locomotion reward,
by which open-loop bodies are scored; the heading channels are 0).

The bodies' frame: every body is simulated as one robot, all its voxels (every component: pass
``freeform.body.largest_component(grids)`` for the connected robot alone, as the design env's bodies are), cropped to
its bounding box (the layout's ``lattice``, with the crop ``origin`` in the body's grid), and the controller sees and acts on that box, padded to
the largest box of the batch, ``box = (Bx, By, Bz)``: a 78-voxel design body of a 20³ grid sits in a box of a few
hundred cells instead of 8,000 (the dense ρ³ grid made a rollout of 128 bodies gigabytes). A cell of the box is
cell ``box_cell + origin`` of the body's grid (:meth:`ControlEnv.to_grid` maps any per-cell values back).

Observations ``[N, C, Bx, By, Bz]`` float32 (``OBS_CHANNELS``; zero in empty cells): the cell is filled, its
material / k, whether it is actuated (its command acts), its position relative to the centre of mass and its
velocity (voxel lengths and voxel lengths per actuation period), its mean link strain, ground contact; then task
features broadcast to every filled cell: the heading's cos and sin, the episode's progress in [0, 1], and the
actuation clock's phase (sin and cos of 2π·t / ``sim.temp_period``, t the simulated time since placement): the
rhythm the open-loop sine follows, so that a controller can reproduce that gait and need not invent a rhythm.

Actions ``[N, Bx·By·Bz]``, one command per cell; only the actuated voxels' entries act. With
``control.residual`` an action is a correction to the open-loop gait (``SimConfig(actuation="residual")``): each
actuated voxel's actuation is its material's sine, computed every simulator step as open loop, plus the action
(clipped to [−2, 2]), the sum kept in the sine's range; the observation gains the sine at the coming period's
midpoint as a last channel, ``open_loop`` (``RESIDUAL_CHANNELS``). Zero actions are the body's open-loop gait, bit
for bit, so a controller starts from what the body already does and learns what to add to it. PPO's distribution is a
:class:`~freeform.distributions.MaskedDiagGaussian` (``action_distribution``): the policy reads the
``actuated`` channel (``mask_channel``) as the mask, so log-probabilities, entropy and KL count the entries that act.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from freeform.body import metrics
from freeform.distributions import MaskedDiagGaussian
from freeform.envs.control_config import HEADINGS, ControlConfig, same_config
from freeform.envs.response import RESPONSE_CHANNELS, GaitResponse, response_window
from freeform.envs.symmetry import PLANAR_VECTORS, PlanarSymmetry
from freeform.sim import SimConfig, Simulator
from freeform.sim.config import material_table
from freeform.sim.engine import Engine, Readout
from freeform.sim.state import MT, RUNNING, SENSE

OBS_CHANNELS = ("filled", "material", "actuated", "rel_x", "rel_y", "rel_z", "vel_x", "vel_y", "vel_z", "strain", "contact",
                "heading_cos", "heading_sin", "progress", "clock_sin", "clock_cos")
RESIDUAL_CHANNELS = (*OBS_CHANNELS, "open_loop")
"""A residual control env's channels (``ControlConfig.residual``): the last one is each actuated voxel's open-loop
command over the coming period, the base its action is added to."""
CRITIC_STATE = ("dx", "dy", "dz", "r11", "r21", "r31", "r12", "r22", "r32", "time_left")
"""The privileged critic's entries per body (``ControlConfig.privileged_critic``): the centre of mass's displacement
since the episode's start (voxel lengths), the body's orientation — the first two columns of the rotation that best
maps its voxels' rest offsets onto their offsets now (Kabsch's, about the centre of mass) — and the fraction of the
episode left."""


def arch_for(device: torch.device) -> str:
    """The simulator's backend for an env whose tensors live on ``device``: the physics runs where the observations
    are wanted (CUDA for a CUDA device, else the CPU)."""
    return "cuda" if device.type == "cuda" else "cpu"


class ControlEnv:
    """``num_envs`` bodies (uint8 grids ``[N, ρ, ρ, ρ]``, every one non-empty) under closed-loop control: a
    :class:`freeform.envs.VecEnv` whose action is one command per cell of the bodies' box (``action_dim`` =
    Bx·By·Bz, C order) and whose observation is ``[N, len(channels), Bx, By, Bz]`` (``OBS_CHANNELS``, or with
    ``control.residual`` ``RESIDUAL_CHANNELS``). ``action_mask [N, Bx·By·Bz]``
    marks the cells whose command acts (actuated voxels), as the observation's ``actuated`` channel does.

    sim: the simulation (its ``actuation`` is set to "command"; burn_in and duration come from ``control``), run
        on the CPU, or on CUDA for a CUDA ``device``.
    box: pad every body's box to this one (default: the largest body's), e.g. to run a controller trained on other
        bodies whose box it was built for; a body larger than it is refused.
    seed, first_env: episode e's headings are drawn from ``numpy.random.default_rng([seed, e])``, environment i
        taking draw ``first_env + i`` — so a data-parallel rank holding environments ``first_env …`` draws what
        one process would, and the episode count is the env's whole random state (:meth:`state_dict`). An array
        ``[N]`` gives each environment's draw (a co-design env's bodies that are not empty).
    simulator: the ``Simulator`` to run on (its config must be this env's ``sim_config``; any backend): a co-design
        env builds one control env per episode on one simulator.

    At the end of every episode ``info`` holds, besides ``truncated`` and ``final_obs``, the episode records'
    ``final_grids`` (the bodies' grids, as given) and ``metrics`` (their body metrics, ``freeform.body``).
    """

    def __init__(self, grids: torch.Tensor | np.ndarray, sim: SimConfig | None = None,
                 control: ControlConfig | None = None, seed: int = 0, device: str | torch.device = "cpu",
                 first_env: int | np.ndarray = 0, box: tuple[int, int, int] | None = None,
                 simulator: Simulator | None = None):
        grids = torch.as_tensor(np.asarray(grids)).to(torch.uint8)
        if grids.dim() != 4 or not (grids.shape[1] == grids.shape[2] == grids.shape[3]):
            raise ValueError(f"grids must be uint8 [N, ρ, ρ, ρ], got shape {tuple(grids.shape)}")
        if grids.shape[0] == 0 or not grids.flatten(1).any(dim=1).all():
            raise ValueError("every body must have at least one voxel (an empty grid has nothing to control)")
        self.control = control or ControlConfig()
        self.control.validate()
        self.sim_config = self.simulation(sim or SimConfig(), self.control)
        self.grids = grids.cpu()
        self.num_envs, self.rho = int(grids.shape[0]), int(grids.shape[1])
        self.device = torch.device(device)
        if simulator is not None and simulator.config != self.sim_config:
            raise ValueError("simulator: its config is not this control env's (SimConfig with actuation='command', "
                             "burn_in 0 and the episode's duration: ControlEnv.sim_config)")
        self.simulator = simulator if simulator is not None else Simulator(self.sim_config, arch=arch_for(self.device))
        self.layout = self.simulator.layout(self.grids)
        self._place_in_box(box)
        self._index_cells()
        self._body_features()
        draws = np.asarray(first_env, dtype=np.int64) + (np.arange(self.num_envs) if np.ndim(first_env) == 0 else 0)
        if draws.shape != (self.num_envs,) or (draws < 0).any():
            raise ValueError(f"first_env must be an int >= 0 or [{self.num_envs}] ints >= 0, got {first_env!r}")
        self.seed, self._draws = int(seed), draws
        self.episode = -1
        """Episodes started so far − 1: the index of the current episode (its headings' draw)."""
        self._metrics = {k: v.float().to(self.device) for k, v in metrics(self.grids).items()}  # (the records')
        self._final_grids = self.grids.to(self.device)
        self.engine: Engine | None = None
        self._after_period: Callable[[], None] | None = None  # (record: a frame between the periods)
        self._settled: dict[str, Any] | None = None  # the engine's state after the burn-in (Engine.snapshot)
        self.t = self._periods = 0
        self.heading = np.zeros(self.num_envs)
        self._com = self._start = np.zeros((self.num_envs, 3))
        self.observation: Any = None
        """The observation last returned (by ``reset`` or ``step``, or after ``load_state_dict``)."""

    def _place_in_box(self, box: tuple[int, int, int] | None) -> None:
        """Each body in its box (the largest body's, or ``box``) and the observation's and action's shapes."""
        lay = self.layout
        self._robot = lay.voxel_robot.astype(np.int64)
        self._lattice = lay.lattice.astype(np.int64)  # each voxel's cell in its robot's box
        need = tuple(int(b) for b in self._lattice.max(0) + 1)
        if box is not None:
            box = tuple(int(b) for b in box)
            if len(box) != 3 or any(b < n for b, n in zip(box, need, strict=True)):
                raise ValueError(f"box {box} does not hold these bodies, whose largest box is {need}")
        self.box = box if box is not None else need
        """``(Bx, By, Bz)``: the largest body's box (or the one given); every body's box sits at its corner (cell
        0, 0, 0)."""
        if not np.array_equal(lay.body_of_robot, np.arange(self.num_envs)):  # (rewards and headings are per robot)
            raise ValueError("ControlEnv simulates each body as one robot, in the order of the grids")
        self.origin = torch.from_numpy(lay.origin.astype(np.int64))
        """``[N, 3]`` where each body's box starts in its grid (the layout's crop origin)."""
        self.channels = ((RESIDUAL_CHANNELS if self.control.residual else OBS_CHANNELS)
                         + (RESPONSE_CHANNELS if self.control.response else ()))
        """The observation's channels, in order."""
        self._planar_columns = tuple((self.channels.index(x), self.channels.index(y)) for x, y in PLANAR_VECTORS
                                     if x in self.channels and y in self.channels and x != "heading_cos")
        """The observation's planar vectors but the heading (``[x, y]`` channel pairs): what the heading's frame
        turns."""
        self.observation_shape: Any = (len(self.channels), *self.box)
        if self.control.privileged_critic:
            self.observation_shape = {"policy": self.observation_shape, "critic": (len(CRITIC_STATE),)}
        self.cells = math.prod(self.box)
        """Cells of the box, Bx·By·Bz."""
        self.action_channels = 2 if self.control.stroke_periods else 1
        """Numbers per cell of an action: a command, or a stroke's (a, b) (``stroke_periods``)."""
        self.action_dim = self.cells * self.action_channels

    def _index_cells(self) -> None:
        """Each voxel's cell in its body's box, in the flat observation and in its grid; the action mask."""
        lay, robot, lattice = self.layout, self._robot, self._lattice
        body = lay.body_of_robot[robot]
        self._body = body
        self._cell = (lattice[:, 0] * self.box[1] + lattice[:, 1]) * self.box[2] + lattice[:, 2]  # C order in the box
        self._flat = body * self.cells + self._cell  # into [N·cells]
        grid = lattice + lay.origin[robot].astype(np.int64)
        self._grid_cell = (grid[:, 0] * self.rho + grid[:, 1]) * self.rho + grid[:, 2]
        # the observation is assembled where the policy reads it (on a GPU: no [N, C, box] grid built on the host and
        # copied over every control step — at N = 1,024 bodies of ρ = 20 that was 0.5 GB a step, 50 of its 72 ms)
        self._flat_t = torch.from_numpy(self._flat).to(self.device)
        self._body_t, self._cell_t = torch.from_numpy(body).to(self.device), torch.from_numpy(self._cell).to(self.device)
        self._actuated = material_table(self.sim_config)[MT.CTE][lay.material] != 0
        self.action_mask = torch.zeros(self.num_envs * self.cells, dtype=torch.bool)
        self.action_mask[torch.from_numpy(self._flat)] = torch.from_numpy(self._actuated)
        self.action_mask = self.action_mask.view(self.num_envs, self.cells).repeat(1, self.action_channels).to(self.device)
        self.action_distribution = MaskedDiagGaussian(self.action_dim)
        """What PPO trains: a Gaussian per cell, counted where the ``actuated`` channel (``mask_channel``) is 1."""
        self.mask_channel = OBS_CHANNELS.index("actuated")
        self.filled_channel = OBS_CHANNELS.index("filled")

    def _body_features(self) -> None:
        """What the sensing reads of each voxel that does not change: its rest offset from its body's centre, its
        material, whether it is actuated, its open-loop phase; the physics' length and speed scales."""
        lay, robot, lattice = self.layout, self._robot, self._lattice
        centre = np.zeros((self.num_envs, 3))
        np.add.at(centre, robot, lattice.astype(np.float64))
        centre /= np.bincount(robot, minlength=self.num_envs)[:, None]
        self._rest = lattice - centre[robot]  # each voxel's rest offset from its body's centre (voxel lengths)
        self._material = lay.material.astype(np.float64) / len(self.sim_config.materials)
        self._actuated = self._actuated.astype(np.float64)
        self.material_phases = (0.0, *(m.phase for m in self.sim_config.materials))
        """Each material index's open-loop phase in cycles (index 0: empty), as the simulator plays it."""
        self._phase = np.array(self.material_phases)[lay.material]  # cycles
        self._open_loop = np.zeros(lay.num_voxels)  # the sine mid-way through the coming period (residual control)
        L = self.sim_config.voxel_size
        self._length, self._speed = L, L / self.sim_config.temp_period
        window = response_window(self.sim_config.temp_period, self.control.period) if self.control.response else 0
        self._response = GaitResponse(lay.num_voxels, window) if window else None  # (control.response's samples)

    @staticmethod
    def simulation(sim: SimConfig, control: ControlConfig) -> SimConfig:
        """What a control env simulates: ``sim`` with commanded actuation (``residual``: the sine corrected by the
        commands), no burn-in of its own, and a duration past the episode's end (the episode's own clock: the
        simulator never stops a robot before the episode ends)."""
        config = replace(sim, actuation="residual" if control.residual else "command", burn_in=0.0,
                         duration=control.burn_in + control.steps * control.decision_seconds + 1.0)
        config.validate("sim")
        return config

    @staticmethod
    def physics_differences(theirs: SimConfig, mine: SimConfig, control: ControlConfig, whose: str,
                            here: str = "here") -> str:
        """Where an env of ``theirs`` simulates another physics than one of ``mine`` under ``control`` — each field,
        as ``sim.<field>: <theirs> in <whose>, <mine> <here>``, joined by "; " — or "" where none. What the env
        simulates is compared (:meth:`simulation`: the episode sets the actuation, burn-in and duration), and how
        it runs may differ (schedule, backend: ``SimConfig.physics_differences``). The one check of every reuse
        of controllers across runs: teacher runs and their pools, selections, per-body references."""
        played, mine_ = (ControlEnv.simulation(s, control) for s in (theirs, mine))
        return "; ".join(f"sim.{k}: {getattr(played, k)!r} in {whose}, {getattr(mine_, k)!r} {here}"
                         for k in played.physics_differences(mine_))

    # ------------------------------------------------------------------ the VecEnv
    def reset(self, seed: int | None = None, episode: int | None = None) -> torch.Tensor:
        """Start the next episode (or episode ``episode``): the bodies placed and settled for ``control.burn_in``
        seconds (zero commands), the episode's headings drawn. ``seed``: start over as episode 0 of that seed."""
        if seed is not None:
            self.seed, self.episode = int(seed), -1
        self.episode = self.episode + 1 if episode is None else int(episode)
        return self._start_episode()

    def _start_episode(self) -> torch.Tensor:
        if self._settled is not None and self.engine is not None and not self.engine.current:
            # someone built another engine on this env's simulator (a population env's other cohort): a fresh
            # engine of the same layout takes the settled state back, bit for bit, without settling again
            self.engine = self.simulator.engine(self.layout)
        if self._settled is None:  # the first episode settles the bodies; the others start from that state
            self.engine = self.simulator.engine(self.layout)
            self._burn_in()
            self._settled = self.engine.snapshot()
            self._settled_response = self._response.state() if self._response is not None else None
        else:  # (the burn-in is deterministic: the same state, bit for bit, without its cost)
            self.engine.restore(self._settled)
            if self._response is not None:
                self._response.restore(self._settled_response)
        if self.control.headings == "random":
            draw = np.random.default_rng([self.seed, self.episode]).uniform(0.0, 2 * math.pi, self._draws.max() + 1)
            self.heading = draw[self._draws]
        else:
            self.heading = np.zeros(self.num_envs)
        self.t = self._periods = 0
        self._command = np.zeros(self.layout.num_voxels)  # (the settled state's: commands start at 0)
        # what each muscle receives as the episode starts (residual: the open-loop sine, walked through the burn-in)
        self._received = self._actuated * np.sin(2 * math.pi * (self.control.burn_in / self.sim_config.temp_period
                                                                + self._phase)) if self.control.residual else 0.0
        obs, self._com = self._observe()
        self._start = self._com.copy()  # (headings "any": the distance is from here)
        return obs

    def _burn_in(self) -> None:
        """Settle for ``control.burn_in`` s under zero commands; with the response, its last whole control periods one
        by one, each but the last sensed (the first observation senses that): the first decision reads the gait."""
        period = self.control.period
        periods = int(math.floor(self.control.burn_in / period + 1e-9)) if self._response is not None else 0
        if self.control.burn_in - periods * period > 0:
            self.engine.advance_time(self.control.burn_in - periods * period)
        for k in range(periods):
            readout = self.engine.control_step(np.zeros(self.layout.num_voxels), period,
                                               ramp=period if self.control.ramp else 0.0)
            if k < periods - 1:
                self._sense(readout[0], self.control.burn_in - (periods - 1 - k) * period)

    def _sense(self, sensed: np.ndarray, t: float) -> None:
        """The response's sample of the voxels' velocities at ``t`` s since placement."""
        self._response.add(sensed[:, SENSE.span("VEL")] / self._speed, 2 * math.pi * t / self.sim_config.temp_period)

    def symmetry(self, group: str = "ground") -> PlanarSymmetry:
        """The ground's turns and mirrors that map this env's box onto itself (``freeform.envs.symmetry``; ``group``
        one of its ``GROUPS``): by these a distillation turns its samples (``algo.symmetry``)."""
        return PlanarSymmetry.of(self, group)

    def to_grid(self, values: torch.Tensor) -> torch.Tensor:
        """Per-cell values of the box, ``[N, Bx·By·Bz]`` or ``[N, C, Bx, By, Bz]`` (actions, observations), on the
        bodies' own grids ``[N, ρ, ρ, ρ]`` / ``[N, C, ρ, ρ, ρ]``: each voxel's value in its grid cell, zero
        elsewhere."""
        values = torch.as_tensor(values)
        if values.shape[0] != self.num_envs or values[0].numel() % self.cells:
            raise ValueError(f"values must be [{self.num_envs}, {self.cells}] or [{self.num_envs}, C, *{self.box}] "
                             f"(per cell of the box), got {tuple(values.shape)}")
        lead = values[0].numel() // self.cells
        flat = values.reshape(self.num_envs, lead, self.cells)
        out = values.new_zeros(self.num_envs, lead, self.rho ** 3)
        body, grid_cell, cell = self._indices(values.device)
        out[body, :, grid_cell] = flat[body, :, cell]
        shape = (self.rho,) * 3
        return out.view(self.num_envs, *shape) if values.dim() == 2 else out.view(self.num_envs, lead, *shape)

    def from_grid(self, values: torch.Tensor) -> torch.Tensor:
        """The inverse of :meth:`to_grid` for one value per cell: ``[N, ρ, ρ, ρ]`` (or ``[N, ρ³]``) on the bodies'
        grids → ``[N, Bx·By·Bz]`` in the box (zero in the box's empty cells), e.g. commands chosen on the grid."""
        values = torch.as_tensor(values)
        if values.shape[0] != self.num_envs or values[0].numel() != self.rho ** 3:
            raise ValueError(f"values must be [{self.num_envs}, {self.rho}, {self.rho}, {self.rho}], got "
                             f"{tuple(values.shape)}")
        out = values.new_zeros(self.num_envs, self.cells)
        body, grid_cell, cell = self._indices(values.device)
        out[body, cell] = values.reshape(self.num_envs, -1)[body, grid_cell]
        return out

    def _indices(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each voxel's body, its cell in its grid and its cell in the box, on ``device``."""
        return (self._body_t.to(device), torch.from_numpy(self._grid_cell).to(device), self._cell_t.to(device))

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """``actions`` ``[N, Bx·By·Bz]`` (or ``[N, Bx, By, Bz]``), clipped to [−1, 1]: one control period (with
        ``stroke_periods`` n: ``[N, 2·Bx·By·Bz]``, a stroke's (a, b) per cell, held for n periods)."""
        if self.engine is None:
            raise RuntimeError("call reset() before step()")
        a = torch.as_tensor(actions).detach()
        if a.numel() != self.num_envs * self.action_dim or a.shape[0] != self.num_envs:
            what = "a stroke's (a, b) per cell" if self.control.stroke_periods else "one per cell"
            raise ValueError(f"actions must be [{self.num_envs}, {self.action_dim}] ({what} of the bodies' box "
                             f"{self.box}), got {tuple(a.shape)}")
        # only the cells that hold a voxel are read (the rest are ignored, NaN included)
        flat = self._flat_t if self._flat_t.device == a.device else self._flat_t.to(a.device)
        values = a.reshape(self.num_envs, self.action_channels, self.cells).transpose(0, 1).reshape(
            self.action_channels, -1)[:, flat].to("cpu", torch.float64)
        if not torch.isfinite(values).all():
            raise ValueError("actions must be finite in the cells that hold a voxel")
        values = values.numpy()
        for p in range(self.control.periods_per_step):
            if self.control.stroke_periods:  # the stroke at this period's middle, in each voxel's own phase
                middle = (self.control.burn_in + (self._periods + 0.5) * self.control.period) / self.sim_config.temp_period
                theta = 2 * math.pi * (middle + self._phase)
                readout = self._period(values[0] * np.sin(theta) + values[1] * np.cos(theta))
            else:
                readout = self._period(values[0])
            if self._after_period is not None:
                self._after_period()
            if p < self.control.periods_per_step - 1 and self._response is not None:  # (the last: _observe's)
                self._sense(readout[0], self.control.burn_in + self._periods * self.control.period)
        self.t += 1
        obs, com = self._observe(readout)
        ok = readout.status == RUNNING
        if self.control.headings == "any":  # the distance from the start grows: the return is the final distance
            move = np.hypot(*(com - self._start)[:, :2].T) - np.hypot(*(self._com - self._start)[:, :2].T)
        else:
            move = (com - self._com)[:, 0] * np.cos(self.heading) + (com - self._com)[:, 1] * np.sin(self.heading)
        reward = np.where(ok, move / self._length, 0.0)
        self._com = com
        done = self.t >= self.control.steps
        info: dict[str, Any] = {"heading": torch.from_numpy(self.heading).float().to(self.device),
                                "failed": torch.from_numpy(~ok).to(self.device)}
        if done:
            info["truncated"] = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
            info["final_obs"] = obs
            info["final_grids"], info["metrics"] = self._final_grids, self._metrics
            obs = self.reset()
        dones = torch.full((self.num_envs,), done, dtype=torch.bool, device=self.device)
        return obs, torch.from_numpy(reward).float().to(self.device), dones, info

    def _period(self, commands: np.ndarray) -> Readout:
        """One control period of per-voxel ``commands`` ``[V]``: clipped, limited to a muscle's bandwidth, run."""
        reach = 2.0 if self.control.residual else 1.0  # (a correction of ±2 reaches the range from any phase)
        target = np.clip(commands, -reach, reach)
        if self.control.command_rate is not None:  # a muscle's bandwidth: at most rate·period per period
            most = self.control.command_rate * self.control.period
            if self.control.residual:  # the muscle receives the sine plus the correction: that is what is limited
                end = (self.control.burn_in + (self._periods + 1) * self.control.period) / self.sim_config.temp_period
                sine = self._actuated * np.sin(2 * math.pi * (end + self._phase))
                received = np.clip(np.clip(sine + target, -1.0, 1.0), self._received - most, self._received + most)
                target, self._received = received - sine, received
            else:
                target = np.clip(target, self._command - most, self._command + most)
        self._command = target
        self._periods += 1
        return self.engine.control_step(target, self.control.period,
                                        ramp=self.control.period if self.control.ramp else 0.0)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The env's state between episodes (a run's checkpoint: PPO's rollouts are whole episodes, so every epoch
        ends at an episode boundary): the episode count and, per environment, the bodies, checked on load. The
        settled state is not saved: settling is deterministic and :meth:`load_state_dict` settles again."""
        if self.t != 0:
            raise ValueError(f"a ControlEnv saves its state between episodes, and this one is {self.t} control steps "
                             f"into episode {self.episode}: make PPO's rollout_steps a multiple of the episode's "
                             f"{self.control.steps} steps (a run's agent.rollout_steps)")
        return {"per_env": {"grids": self.grids.clone()}, "episode": self.episode, "seed": self.seed,
                "config": self._config()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict`: the same bodies and configuration, at the start of the saved episode."""
        grids = torch.as_tensor(state["per_env"]["grids"]).cpu()
        if grids.shape != self.grids.shape or not torch.equal(grids, self.grids):
            raise ValueError("the state's bodies (per_env.grids) are not this environment's: a control run resumes "
                             "on the bodies it was trained on")
        if not same_config(state.get("config"), self._config()):
            raise ValueError(f"state config {state.get('config')} does not match this environment's {self._config()}: "
                             "build the env with the saved run's config (a resume takes it from the checkpoint)")
        self.seed, self.episode = int(state["seed"]), int(state["episode"])
        self._start_episode()

    def _config(self) -> dict[str, Any]:
        return {"control": vars(self.control).copy(), "box": list(self.box)}

    # ------------------------------------------------------------------ branches
    # What an episode carries from step to step besides the engine: the clock, the commands in flight (a muscle's
    # bandwidth and ramp start from them), centres of mass, headings, the sensed response and the next observation
    # (the seed and episode too: a branch may run past the episode's end, which draws the next one's headings).
    # The open-loop channel is not here: every observation recomputes it.
    EPISODE_STATE = ("seed", "episode", "t", "_periods", "heading", "_command", "_received", "_com", "_start",
                     "_response", "observation")

    def snapshot(self) -> dict[str, Any]:
        """The episode's whole state now, mid-episode too: the engine's (:meth:`Engine.snapshot`) and
        :attr:`EPISODE_STATE`. :meth:`restore` returns to it, so that what follows is what would have followed, bit
        for bit: several futures of one state (what each of several controllers would do from here) cost one
        episode each and no settling. Between episodes :meth:`state_dict` is the checkpoint; this is for branching
        within one."""
        if self.engine is None:
            raise RuntimeError("call reset() before snapshot()")
        return {"engine": self.engine.snapshot(),
                "env": copy.deepcopy({name: getattr(self, name) for name in self.EPISODE_STATE})}

    def restore(self, snapshot: dict[str, Any]) -> torch.Tensor:
        """Return to :meth:`snapshot` (of this env); returns the observation the next action acts on."""
        if self.engine is None or not self.engine.current:
            raise RuntimeError("restore(): this env's engine is gone (another env built one on its simulator since "
                               "the snapshot, or it never had one): take snapshots and restore them on one env, "
                               "with no other env stepped on its simulator in between")
        self.engine.restore(snapshot["engine"])
        for name, value in copy.deepcopy(snapshot["env"]).items():  # (a copy: the snapshot restores again)
            setattr(self, name, value)
        return self.observation

    @torch.no_grad()
    def record(self, act: Any, robot: int = 0, every: int | None = None,
               rewarded: Callable[[torch.Tensor], None] | None = None) -> tuple[Any, np.ndarray, float]:
        """One episode of robot ``robot`` under ``act`` (``[N, C, Bx, By, Bz]`` → ``[N, Bx·By·Bz]``; ``rewarded`` is
        told each step's rewards ``[N]``) to look at: a :class:`freeform.sim.simulator.Recording` with a frame after the
        burn-in, every ``every`` control periods (None: every action's) and the last, the commands its actuated voxels
        received ``[steps, voxels]``, and its return. A new episode, :meth:`step`'s bit for bit (frames between periods)."""
        from freeform.sim.simulator import Recording

        every = self.control.periods_per_step if every is None else every
        if not (isinstance(every, int) and every >= 1):
            raise ValueError(f"every must be a whole number of control periods >= 1, got {every!r}")
        obs, lay = self.reset(), self.layout
        mine = lay.voxel_robot == robot
        positions, orientations = [self.engine.positions()[mine]], [self.engine.orientations()[mine]]
        taken, periods, last = [0], 0, self.control.steps * self.control.periods_per_step

        def frame() -> None:  # (after each control period, before an episode's end resets the env; the last always)
            nonlocal periods
            periods += 1
            if periods % every == 0 or periods == last:
                positions.append(self.engine.positions()[mine])
                orientations.append(self.engine.orientations()[mine])
                taken.append(periods)

        commands, total = [], 0.0
        self._after_period = frame
        try:
            for _ in range(self.control.steps):
                action = torch.as_tensor(act(obs)).reshape(self.num_envs, -1)
                commands.append(action[robot][self.action_mask[robot]].clamp(-1.0, 1.0).cpu().numpy())
                obs, reward, _, _ = self.step(action)
                if rewarded is not None:
                    rewarded(reward)
                total += float(reward[robot])
        finally:
            self._after_period = None
        recording = Recording(times=self.control.burn_in + self.control.period * np.array(taken, dtype=np.float64),
                              voxel_size=self.sim_config.voxel_size, lattice=[lay.lattice[mine]],
                              materials=[lay.material[mine]], positions=[np.stack(positions).astype(np.float32)],
                              orientations=[np.stack(orientations).astype(np.float32)])
        return recording, np.stack(commands), total

    # ------------------------------------------------------------------ sensing
    def _observe(self, readout: Readout | None = None) -> tuple[torch.Tensor, np.ndarray]:
        """The observation ``[N, C, Bx, By, Bz]`` and each robot's centre of mass ``[N, 3]`` (m) from what the
        engine sensed on the device (a control step's readout, else ``Engine.sense``: one kernel, one copy back);
        the host adds the per-body constants and scatters into the box."""
        R = self.num_envs
        sensed, com = (self.engine.sense() if readout is None else readout)[:2]
        progress = self.t / self.control.steps
        start = self.control.burn_in + self.t * self.control.decision_seconds
        clock = 2 * math.pi * start / self.sim_config.temp_period
        r = self._robot
        # (no heading to observe when any direction counts, nor in the heading's frame, where it is +x)
        seen = float(self.control.headings != "any" and self.control.frame == "world")
        if self.control.residual:  # what the corrections are added to: the sine, mid-way through the period
            middle = (start + 0.5 * self.control.period) / self.sim_config.temp_period
            self._open_loop = self._actuated * np.sin(2 * math.pi * (middle + self._phase))
        if self._response is not None:
            self._sense(sensed, start)
        features = np.concatenate([
            np.ones((len(r), 1)), self._material[:, None], self._actuated[:, None],
            sensed[:, SENSE.span("REL")] / self._length, sensed[:, SENSE.span("VEL")] / self._speed,
            sensed[:, SENSE.STRAIN:SENSE.STRAIN + 1], sensed[:, SENSE.CONTACT:SENSE.CONTACT + 1],
            np.stack([seen * np.cos(self.heading)[r], seen * np.sin(self.heading)[r], np.full(len(r), progress),
                      np.full(len(r), math.sin(clock)), np.full(len(r), math.cos(clock))], 1),
            *([self._open_loop[:, None]] if self.control.residual else []),
            *([self._response.coefficients()] if self._response is not None else []),
        ], 1)
        if self.control.frame == "heading":
            self._to_heading_frame(features, self.heading[r], self._planar_columns)
        obs = torch.zeros((R, len(self.channels), self.cells), dtype=torch.float32, device=self.device)
        obs[self._body_t, :, self._cell_t] = torch.from_numpy(features).float().to(self.device)  # channel-first
        obs = obs.view(R, len(self.channels), *self.box)
        if self.control.privileged_critic:
            obs = {"policy": obs, "critic": self._critic_state(sensed, com)}
        self.observation = obs  # (what the next action acts on, once step or reset returns it)
        return obs, com

    @staticmethod
    def _to_heading_frame(rows: np.ndarray, heading: np.ndarray, columns: tuple[tuple[int, int], ...]) -> None:
        """Turn the planar vectors of ``rows [n, …]`` (each pair of ``columns``: x, y) about z by −``heading [n]``
        (radians), in place: x along the heading (``ControlConfig.frame``)."""
        c, s = np.cos(heading), np.sin(heading)
        for x, y in columns:
            vx, vy = rows[:, x].copy(), rows[:, y].copy()
            rows[:, x], rows[:, y] = c * vx + s * vy, c * vy - s * vx

    def _critic_state(self, sensed: np.ndarray, com: np.ndarray) -> torch.Tensor:
        """``CRITIC_STATE`` ``[N, 10]`` float32: displacement since the episode's start, orientation, time left."""
        moved = (com - (self._start if self.t > 0 else com)) / self._length
        now = sensed[:, SENSE.span("REL")] / self._length
        cov = np.zeros((self.num_envs, 3, 3))
        np.add.at(cov, self._robot, self._rest[:, :, None] * now[:, None, :])  # Σ rest ⊗ now, per body
        u, _, vt = np.linalg.svd(cov)
        flip = np.sign(np.linalg.det(np.transpose(vt, (0, 2, 1)) @ np.transpose(u, (0, 2, 1))))
        vt[:, 2] *= np.where(flip == 0, 1.0, flip)[:, None]  # a rotation, not a reflection
        rotation = np.transpose(vt, (0, 2, 1)) @ np.transpose(u, (0, 2, 1))  # rest → now
        left = np.full((self.num_envs, 1), 1.0 - self.t / self.control.steps)
        state = np.concatenate([moved, rotation[:, :, 0], rotation[:, :, 1], left], 1)
        if self.control.frame == "heading":  # (the displacement and the body's axes: vectors in the ground plane)
            self._to_heading_frame(state, self.heading, ((0, 1), (3, 4), (6, 7)))
        return torch.from_numpy(state).float().to(self.device)


def open_loop_moves(grids: torch.Tensor | np.ndarray, sim: SimConfig | None = None,
                    control: ControlConfig | None = None, arch: str = "cpu") -> np.ndarray:
    """What the bodies' open-loop sine gaits do in a control episode's window: each body's centre of mass move in
    the ground plane (x, y) from ``control.burn_in`` to ``burn_in + duration`` (the sine from t = 0, as every
    open-loop body), in voxel lengths ``[N, 2]``, 0 for a robot that failed and for an empty grid."""
    sim, control = sim or SimConfig(), control or ControlConfig()
    grids = torch.as_tensor(np.asarray(grids)).to(torch.uint8)
    out = np.zeros((len(grids), 2))
    config = replace(sim, actuation="sine", burn_in=0.0, duration=control.burn_in + control.duration + 1.0)
    simulator = Simulator(config, arch=arch)
    layout = simulator.layout(grids)
    if layout.num_robots == 0:
        return out
    engine = simulator.engine(layout)
    if control.burn_in > 0:
        engine.advance_time(control.burn_in)
    start = engine.sense()
    engine.advance_time(control.duration)
    end = engine.sense()
    ok = (end.status == RUNNING)[:, None]
    out[layout.body_of_robot] = np.where(ok, (end.com - start.com)[:, :2] / sim.voxel_size, 0.0)  # (empty grid: no robot)
    return out


def open_loop_displacement(grids: torch.Tensor | np.ndarray, sim: SimConfig | None = None,
                           control: ControlConfig | None = None, arch: str = "cpu",
                           headings: np.ndarray | None = None, planar: bool = False,
                           moves: np.ndarray | None = None) -> np.ndarray:
    """The bodies' open-loop gaits (:func:`open_loop_moves`, or ``moves`` computed before) as one figure per body
    ``[N]``, voxel lengths: the move along +x, or along ``headings [N]`` (radians from +x towards +y: a steering
    task's figure), or, ``planar``, the distance in the ground plane whatever the direction (an open-loop body's own
    best heading). The figure a controller is compared with."""
    moves = open_loop_moves(grids, sim, control, arch) if moves is None else np.asarray(moves, np.float64)
    if planar:
        return np.hypot(moves[:, 0], moves[:, 1])
    heading = np.zeros(len(moves)) if headings is None else np.asarray(headings, np.float64)
    return moves[:, 0] * np.cos(heading) + moves[:, 1] * np.sin(heading)


__all__ = ["HEADINGS", "OBS_CHANNELS", "RESIDUAL_CHANNELS", "ControlConfig", "ControlEnv", "arch_for", "open_loop_displacement", "open_loop_moves"]
