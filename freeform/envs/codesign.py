"""Body and brain in one episode (issue 32's environment): ``design_steps`` design actions build a body on the ρ³
grid, as in the design env, then ``control.steps`` control steps drive that body, as in the control env — one
batched :class:`freeform.envs.VecEnv` that one PPO learns end to end (``docs/codesign.md``).

Everything is on the design grid, so that both stages see one frame and one tensor shape:

* Observations ``[N, len(CODESIGN_CHANNELS), ρ, ρ, ρ]`` float32: ``stage`` (0 while designing, 1 while
  controlling, on every cell), ``design_progress`` (t / T while designing, 1 after), ``grid`` (each cell's material
  index, the design so far / the finished design), then the control env's channels (``OBS_CHANNELS``; with
  ``control.residual`` ``RESIDUAL_CHANNELS``) moved from the body's box to its grid cells (``ControlEnv.to_grid``),
  zero while designing.
* Actions ``[N, 3 + k + ρ³]``: the design action ``[x, y, z, w_0 … w_{k−1}]`` (the design env's), then one command
  per grid cell (with ``control.stroke_periods``: ``[N, 3 + k + 2ρ³]``, a stroke's a for every cell, then its b).
  A design step reads the first part, a control step the second (on the body's voxels: a voxel not in the body's
  largest component, like an empty cell, has no command). The distribution is a
  :class:`~freeform.distributions.MaskedDiagGaussian` over all of it; the policy's mask is the design part
  while designing and the actuated voxels while controlling (``CodesignActorCritic``), so each step's
  log-probability, entropy and KL count the entries that act.
* Rewards: 0 for a design step; a control step's is the control env's, the body's centre of mass's move along its
  heading in voxel lengths. The return is the move over the control window.

A design whose body is empty cannot be controlled: its control steps have reward 0 and nothing acts, and its episode
ends with the others (every episode ends together, as the records expect). At the end ``info`` holds the records'
``final_grids`` (the designs), ``bodies``, ``metrics``, and ``truncated`` / ``final_obs`` (the time limit: PPO
bootstraps).

Each episode builds a control env of the new bodies on one simulator (the bodies settle for ``control.burn_in``
seconds first, commands 0); its headings are episode e's draw of ``default_rng([seed, e])``, environment i taking
draw ``first_env + i``, so that the episode count is the env's whole random state, as in the control env.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from freeform.body import bodies_and_metrics, serial_on_cpu
from freeform.distributions import MaskedDiagGaussian
from freeform.envs.control import (
    OBS_CHANNELS,
    RESIDUAL_CHANNELS,
    ControlConfig,
    ControlEnv,
    arch_for,
    same_config,
)
from freeform.envs.design import DesignEnv, EnvConfig
from freeform.sim import SimConfig, Simulator

CODESIGN_CHANNELS = ("stage", "design_progress", "grid", *OBS_CHANNELS)
STAGE, DESIGN_PROGRESS, GRID = 0, 1, 2
CONTROL = slice(3, 3 + len(OBS_CHANNELS))
"""The control env's channels within a co-design observation (``residual``: one more, ``RESIDUAL_CHANNELS``)."""


class CodesignEnv:
    """``num_envs`` design-then-control episodes (module docstring), from the config objects a run has: ``design``,
    the design env's setting (a run's ``env`` section, ``freeform.envs.design.EnvConfig``: ``resolution``, ``steps``
    design steps, ``bundle_size``, ``action_bound``, ``mirror_y``; its ``num_envs`` is not read — a data-parallel
    rank holds ``num_envs`` of them, from ``first_env`` on), ``materials`` (``task.materials``, k incl. empty),
    ``sim`` and ``control``: the control env's (``control.headings`` "fixed": +x, "random": steering)."""

    def __init__(self, num_envs: int, design: EnvConfig | None = None, materials: int = 4,
                 sim: SimConfig | None = None, control: ControlConfig | None = None, *, seed: int = 0,
                 device: str | torch.device = "cpu", first_env: int = 0) -> None:
        if design is None:  # the CPU co-design setting
            design = EnvConfig(resolution=8, steps=20, bundle_size=2, action_bound=2.0, mirror_y=False)
        resolution, design_steps = design.resolution, design.steps
        self.design = DesignEnv(num_envs, design, materials=materials, device="cpu", compute_metrics=False)
        self.control = control or ControlConfig()
        self.control.validate()
        if not (isinstance(first_env, int) and first_env >= 0):
            raise ValueError(f"first_env must be an int >= 0, got {first_env!r}")
        self.num_envs, self.rho, self.materials = num_envs, resolution, materials
        self.design_steps, self.control_steps = design_steps, self.control.steps
        self.steps = design_steps + self.control_steps
        """Steps per episode: T design steps, then the control steps."""
        self.design_dim = 3 + materials
        self.action_channels = 2 if self.control.stroke_periods else 1
        """Numbers per cell of a control action: a command, or a stroke's (a, b) (``control.stroke_periods``)."""
        self.action_dim = self.design_dim + self.action_channels * resolution ** 3
        control_channels = RESIDUAL_CHANNELS if self.control.residual else OBS_CHANNELS
        self.channels = (*CODESIGN_CHANNELS[: CONTROL.start], *control_channels)
        """The observation's channels, in order."""
        self.observation_shape = (len(self.channels), resolution, resolution, resolution)
        self.action_distribution = MaskedDiagGaussian(self.action_dim)
        self.stage_channel, self.grid_channel = STAGE, GRID
        self.control_channels = (CONTROL.start, CONTROL.start + len(control_channels))
        self._control = slice(*self.control_channels)
        self.mask_channel, self.filled_channel = OBS_CHANNELS.index("actuated"), OBS_CHANNELS.index("filled")
        """The channels a policy reads (``CodesignActorCritic.for_env``); mask and filled count from the control
        channels' start."""
        self.device = torch.device(device)
        self.seed, self.first_env = int(seed), first_env
        self.sim = sim or SimConfig()
        self.sim_config = ControlEnv.simulation(self.sim, self.control)
        self.material_phases = (0.0, *(m.phase for m in self.sim_config.materials))
        """Each material's actuation phase in cycles (empty: 0), as the control env's."""
        self.simulator = Simulator(self.sim_config, arch=arch_for(self.device))  # one for every episode's control env
        self.episode = -1
        """The index of the current episode (its headings' draw)."""
        self.t = 0
        self.grids = self.design.grids
        self.controlled: ControlEnv | None = None
        self._alive = torch.zeros(num_envs, dtype=torch.bool)
        self._metrics: dict[str, torch.Tensor] = {}
        self._bodies = torch.zeros_like(self.grids)

    # ------------------------------------------------------------------ the VecEnv
    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Start the next episode: empty grids, the design stage."""
        if seed is not None:
            self.seed, self.episode = int(seed), -1
        self.episode += 1
        self.t = 0
        self.grids = self.design.reset()
        self.controlled = None
        return self._observe()

    @property
    def stage(self) -> str:
        """``"design"`` or ``"control"``: what the next step does."""
        return "design" if self.t < self.design_steps else "control"

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """``actions [N, 3 + k + ρ³]``: a design step reads the first ``3 + k`` columns, a control step the rest."""
        if self.episode < 0:
            raise RuntimeError("call reset() before step()")
        a = torch.as_tensor(actions).detach().to("cpu")
        if tuple(a.shape) != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must be [{self.num_envs}, {self.action_dim}] (3 + k design numbers, then one "
                             f"command per cell of the {self.rho}³ grid), got {tuple(a.shape)}")
        n = self.num_envs
        reward = torch.zeros(n, dtype=torch.float32)
        done = torch.zeros(n, dtype=torch.bool, device=self.device)
        if self.stage == "design":
            with serial_on_cpu("cpu"):
                self.grids = self.design.place_bundles(self.grids, a[:, : self.design_dim])
            self.t += 1
            obs = self._observe() if self.t < self.design_steps else self._start_control()
            return obs, reward.to(self.device), done, {}
        controlled, alive = self.controlled, self._alive
        if controlled is not None:
            obs_c, r, _, info_c = controlled.step(self._box_actions(a[alive]))
            reward[alive] = r.cpu()
            if "final_obs" in info_c:
                obs_c = info_c["final_obs"]
        self.t += 1
        obs = self._observe(obs_c if controlled is not None else None)
        if self.t < self.steps:
            return obs, reward.to(self.device), done, {}
        info = {"truncated": torch.ones(n, dtype=torch.bool, device=self.device), "final_obs": obs,
                "final_grids": self.grids.to(self.device), "bodies": self._bodies.to(self.device),
                "metrics": {k: v.to(self.device) for k, v in self._metrics.items()},
                "failed": (~alive).to(self.device)}
        return self.reset(), reward.to(self.device), torch.ones(n, dtype=torch.bool, device=self.device), info

    def control_view(self) -> SimpleNamespace:
        """The control stage as a controller sees it (``freeform.agents.build_controller``): its observation's
        shape ``[C, ρ, ρ, ρ]`` (the control channels of a co-design observation), those channels and their mask and
        filled channels, the materials' phases, the episode's ``ControlConfig`` and the numbers per cell of an
        action."""
        return SimpleNamespace(observation_shape=(self.control_channels[1] - self.control_channels[0],
                                                  *(self.rho,) * 3),
                               channels=self.channels[self._control], mask_channel=self.mask_channel,
                               filled_channel=self.filled_channel, material_phases=self.material_phases,
                               control=self.control, action_channels=self.action_channels)

    # ------------------------------------------------------------------ stages
    def _box_actions(self, a: torch.Tensor) -> torch.Tensor:
        """The control part of the live bodies' actions ``[M, 3 + k + c·ρ³]`` on their grids → the control env's
        actions ``[M, c·Bx·By·Bz]`` on its box (c numbers per cell, each a block of its own)."""
        assert self.controlled is not None
        part = a[:, self.design_dim:].reshape(a.shape[0], self.action_channels, self.rho ** 3)
        return torch.cat([self.controlled.from_grid(part[:, c]) for c in range(self.action_channels)], dim=1)

    def _start_control(self) -> torch.Tensor:
        """The designs are done: their bodies settle in a control env of their own; the first control observation."""
        bodies, metrics = bodies_and_metrics(self.grids)
        self._bodies, self._metrics = bodies, {k: torch.as_tensor(v).float() for k, v in metrics.items()}
        self._alive = (bodies.flatten(1) > 0).any(dim=1)
        self.controlled = None
        if bool(self._alive.any()):
            draws = self.first_env + torch.nonzero(self._alive).flatten().numpy()
            self.controlled = ControlEnv(bodies[self._alive], sim=self.sim, control=self.control,
                                         seed=self.seed, first_env=draws, simulator=self.simulator)
            obs_c = self.controlled.reset(episode=self.episode)
            return self._observe(obs_c)
        return self._observe()

    def _observe(self, obs_c: torch.Tensor | None = None) -> torch.Tensor:
        """The observation now: stage and design progress from ``t``, the grid, and while controlling the control
        env's observation ``obs_c`` moved to the bodies' grid cells (None: no body to control)."""
        obs = torch.zeros((self.num_envs, *self.observation_shape), dtype=torch.float32)
        obs[:, STAGE] = float(self.t >= self.design_steps)
        obs[:, DESIGN_PROGRESS] = min(self.t / self.design_steps, 1.0)
        obs[:, GRID] = self.grids.float()
        if obs_c is not None:
            assert self.controlled is not None
            obs[self._alive, self._control] = self.controlled.to_grid(obs_c.cpu())
        return obs.to(self.device)

    @property
    def heading(self) -> np.ndarray:
        """Each environment's heading this episode (radians; 0 for an empty body or while designing)."""
        out = np.zeros(self.num_envs)
        if self.controlled is not None:
            out[self._alive.numpy()] = self.controlled.heading
        return out

    @torch.no_grad()
    def record(self, act: Any, robot: int = 0) -> tuple[Any, np.ndarray, float] | None:
        """One episode under ``act`` (observations → actions), for looking at: ``act`` designs the bodies, then
        drives them; robot ``robot``'s control window as ``ControlEnv.record`` gives it (a ``Recording``, its
        commands, its return), or None when its body is empty. Starts a new episode and leaves the env at the
        start of the next one."""
        obs = self.reset()
        for _ in range(self.design_steps):
            obs, *_ = self.step(act(obs))
        controlled, alive = self.controlled, self._alive
        if controlled is None or not bool(alive[robot]):
            self.reset()
            return None

        def act_on_box(obs_c: torch.Tensor) -> torch.Tensor:
            return self._box_actions(torch.as_tensor(act(self._observe(obs_c))).cpu()[alive])

        out = controlled.record(act_on_box, robot=int(alive[:robot].sum()))
        self.reset()
        return out

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The state between episodes (every epoch of whole episodes ends there): the episode count."""
        if self.t != 0:
            raise ValueError(f"a CodesignEnv saves its state between episodes, and this one is {self.t} steps into "
                             f"episode {self.episode}: make PPO's rollout_steps a multiple of the episode's "
                             f"{self.steps} steps")
        return {"episode": self.episode, "seed": self.seed, "config": self._config()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not same_config(state.get("config"), self._config()):
            raise ValueError(f"state config {state.get('config')} does not match this environment's {self._config()}: "
                             "build the env with the saved run's config (a resume takes it from the checkpoint)")
        self.seed, self.episode = int(state["seed"]), int(state["episode"]) - 1
        self.reset()

    def _config(self) -> dict[str, Any]:
        return {"control": vars(self.control).copy(), "resolution": self.rho, "materials": self.materials,
                "design_steps": self.design_steps, "bundle_size": self.design.bundle_size,
                "action_bound": self.design.action_bound, "mirror_y": self.design.mirror_y}


__all__ = ["CODESIGN_CHANNELS", "CONTROL", "CodesignEnv"]
