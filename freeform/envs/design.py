"""The design environment: a batch of voxel grids that a policy fills bundle by bundle (paper §III-A).

Each step every environment places one bundle — a ``b×b×b`` cube of one material, ``b = bundle_size`` — whose
position and material come from the raw action ``[x, y, z, w_0 … w_{k-1}]`` (spec ``design.md``, "Action ->
bundle"). After ``steps`` (T) actions the episode ends for all environments at once: the reward is the task's
score of the final grid, and the environment starts again from an empty grid.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Any

import torch

from freeform.body import bodies_and_metrics, check_grids, largest_component, serial_on_cpu
from freeform.envs.base import ReportsPlacement, Task
from freeform.envs.tasks import VolumeTask

__all__ = ["DesignEnv", "EnvConfig"]


@dataclass
class EnvConfig:
    """The batched design environment, ``freeform.envs.DesignEnv`` (``conf/env/``)."""

    num_envs: int = 256
    """N, environments stepped in lock-step (one robot designed per environment and episode)."""
    resolution: int = 20
    """ρ, edge of the design grid in voxels (even: the network halves it)."""
    steps: int = 100
    """T, actions per episode."""
    bundle_size: int = 2
    """b, edge of the cube of voxels one action paints (even: the bundle is centred between voxels)."""
    action_bound: float = 2.0
    """B, every action component is clipped to [−B, B] and mapped to [0, 1] (spec: 2)."""
    dense_every: int = 0
    """k > 0: dense design rewards — the partial body is scored by the task every k design steps and the
    improvement is the reward (``freeform.envs.DenseDesignReward``; an episode's rewards still sum to the terminal
    reward); 0 = the paper's sparse terminal reward."""
    mirror_y: bool = False
    """Bilateral symmetry: every bundle is placed with its mirror image across the grid's x–z mid-plane, so designs
    are left-right symmetric and travel along ±x on y-symmetric ground (``DesignEnv(mirror_y=...)``); off in the
    paper."""


class DesignEnv:
    """``num_envs`` design grids stepped together in one vectorised operation (a :class:`VecEnv`).

    Observations are the grids of material indices, ``uint8 [N, ρ, ρ, ρ]`` (0 = empty). Actions are raw
    ``float [N, 3 + k]``; every component is mapped through ``f(a) = 1/2 + clip(a, -B, B) / (2B)`` (B =
    ``action_bound``, spec: 2). On axis d the bundle covers the cells ``i`` with ``ρ·f(a_d) - b/2 <= i < ρ·f(a_d)
    + b/2``, i.e. ``ceil(ρ·f) - b/2 … ceil(ρ·f) + b/2 - 1``, clipped to the grid (a bundle over the border is cut,
    not shifted). Its material is ``argmax f(a[3:])`` with ties to the lowest index; material 0 removes. The latest
    action wins.

    The mapping is computed in float32 whatever the action dtype, so that CPU and GPU agree on the cell.

    The reward is 0 except at the last of the ``steps`` actions, which gets ``task.reward(final_grids)``. Then
    ``done`` is all True, the returned observations are the next episode's empty grids, and ``info`` holds the
    finished episodes: ``final_grids`` (``[N, ρ, ρ, ρ] uint8``, the full designs), ``bodies`` (their largest
    components, same shape) and ``metrics`` (``{name: [N] float32}`` from :func:`freeform.body.metrics`; omitted
    when ``compute_metrics`` is False). On the other steps ``info`` is empty.

    The environment never writes into a tensor it has returned, so observations can be stored without copying.
    It is deterministic; ``seed`` is accepted for the VecEnv protocol and kept in the state.
    """

    def __init__(
        self,
        num_envs: int,
        design: EnvConfig | None = None,
        materials: int = 4,
        task: Task | None = None,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        compute_metrics: bool = True,
    ) -> None:
        """
        Args:
            num_envs: N, environments stepped together (``design.num_envs`` is not read: a data-parallel rank
                holds its share).
            design: the design process (:class:`EnvConfig`, default the spec's): ``resolution`` ρ (a positive even
                integer), ``steps`` T, ``bundle_size`` b (a positive even integer <= ρ), ``action_bound`` B of the
                clip mapping (spec: 2, so ~95 % of N(0, 1) centres fall inside the grid) and ``mirror_y``:
                bilateral symmetry — every bundle is also placed at its mirror image across the grid's x–z
                mid-plane (y ↦ ρ − 1 − y), so every design is left-right symmetric. Such a body cannot turn or
                drift sideways on ground that is itself symmetric in y (flat, an x-slope, x-stairs): it travels
                along ±x. Off in the paper.
            materials: k, material count including empty (>= 2; volume task 2, locomotion 4).
            task: scores the final grids; default :class:`VolumeTask`.
            device: where the grids live and every step runs.
            seed: unused by the (deterministic) design process; kept for the protocol and the state.
            compute_metrics: put the body metrics in ``info`` at the end of each episode.
        """
        design = design if design is not None else EnvConfig()
        _check_design(num_envs, design, materials)
        resolution, steps, bundle_size = design.resolution, design.steps, design.bundle_size
        action_bound, mirror_y = design.action_bound, design.mirror_y
        self.num_envs = num_envs
        self.resolution = resolution
        self.materials = materials
        self.steps = steps
        self.bundle_size = bundle_size
        self.action_bound = float(action_bound)
        self.compute_metrics = compute_metrics
        self.mirror_y = mirror_y
        self.task: Task = task if task is not None else VolumeTask()
        self.device = torch.device(device)
        self.seed = seed
        self.observation_shape = (resolution, resolution, resolution)
        self.action_dim = 3 + materials
        try:
            self._task_takes_bodies = "bodies" in inspect.signature(self.task.reward).parameters
        except (TypeError, ValueError):
            self._task_takes_bodies = False

        rho = resolution
        # Flat offset of each grid, and the b offsets of a bundle along one axis (hoisted out of step()).
        self._grid_base = torch.arange(num_envs, device=self.device) * rho**3
        self._bundle_offsets = torch.arange(bundle_size, device=self.device)
        self.grids = torch.zeros((num_envs, rho, rho, rho), dtype=torch.uint8, device=self.device)
        #: Actions taken in the current episode, 0 … steps-1.
        self.t = 0

    # ------------------------------------------------------------------------------------------------ protocol
    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Start new episodes: empty grids ``[N, ρ, ρ, ρ] uint8``."""
        if seed is not None:
            self.seed = seed
        self.grids = torch.zeros_like(self.grids)
        self.t = 0
        return self.grids

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Place one bundle in every grid.

        Args:
            actions: ``[N, 3 + k]`` float, raw (unclipped) policy samples.

        Returns:
            ``(obs [N, ρ, ρ, ρ] uint8, reward [N] float32, done [N] bool, info)`` (see the class docstring).
        """
        actions = self._check_actions(actions)
        n = self.num_envs
        # The env's own ops are small: torch's threads cost more than they gain here (see serial_on_cpu). The
        # task runs outside, with the caller's threading (a simulator may want every core).
        with serial_on_cpu(self.device):
            self.grids = self.place_bundles(self.grids, actions)
            self.t += 1
            if self.t < self.steps:
                reward = torch.zeros(n, dtype=torch.float32, device=self.device)
                done = torch.zeros(n, dtype=torch.bool, device=self.device)
                return self.grids, reward, done, {}
        reward, info = self.score(self.grids)
        with serial_on_cpu(self.device):
            obs = self.reset()
            done = torch.ones(n, dtype=torch.bool, device=self.device)
        return obs, reward, done, info

    def score(self, final_grids: torch.Tensor) -> tuple[torch.Tensor, dict[str, Any]]:
        """Score final grids ``[M, ρ, ρ, ρ] uint8`` as an episode's last step does: ``(reward [M] float32, info)``
        with ``final_grids``, ``bodies`` and (``compute_metrics``) ``metrics``. The evolutionary grid GA scores its
        genomes through it too."""
        m = final_grids.shape[0]
        with serial_on_cpu(self.device):
            info: dict[str, Any] = {"final_grids": final_grids}
            if self.compute_metrics:
                info["bodies"], info["metrics"] = bodies_and_metrics(final_grids)
            else:
                info["bodies"] = largest_component(final_grids)
        if self._task_takes_bodies:
            reward = self.task.reward(final_grids, bodies=info["bodies"])
        else:
            reward = self.task.reward(final_grids)
        reward = torch.as_tensor(reward, dtype=torch.float32).to(self.device)
        if isinstance(self.task, ReportsPlacement):  # each body as the task placed it (quarter turns)
            info["yaw"] = self.task.yaw.to(self.device)
        if tuple(reward.shape) != (m,):
            raise ValueError(
                f"task.reward must return one reward per grid, shape [{m}], got {list(reward.shape)}"
            )
        return reward, info

    # ------------------------------------------------------------------------------------------- the design rule
    def place_bundles(self, grids: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Return a copy of ``grids`` ``[N, ρ, ρ, ρ] uint8`` with one bundle per grid placed by ``actions``
        ``[N, 3 + k]`` (already validated). All grids at once: the b³ covered cells of every grid are written
        with one scatter."""
        rho, b = self.resolution, self.bundle_size
        bound = self.action_bound
        f = 0.5 + actions.to(torch.float32).clamp(-bound, bound) / (2 * bound)  # [N, 3+k] in [0, 1]
        # Lowest covered index per axis: ceil(ρ f) - b/2. Cells past a border are clamped onto the border cell,
        # which is itself covered (the range always meets the grid), so they rewrite it with the same material.
        first = torch.ceil(rho * f[:, :3]).to(torch.int64) - b // 2  # [N, 3]
        cells = (first[:, :, None] + self._bundle_offsets).clamp_(0, rho - 1)  # [N, 3, b]
        flat = (
            self._grid_base[:, None, None, None]
            + cells[:, 0, :, None, None] * (rho * rho)
            + cells[:, 1, None, :, None] * rho
            + cells[:, 2, None, None, :]
        )  # [N, b, b, b]
        material = torch.argmax(f[:, 3:], dim=1).to(torch.uint8)  # first maximum wins ties
        out = grids.clone()
        if self.mirror_y:  # the bundle and its mirror image (y -> ρ-1-y) in the same scatter, of the same material
            mirrored = flat + ((rho - 1) - 2 * cells[:, 1, None, :, None]) * rho
            flat = torch.cat([flat, mirrored], dim=1)
        out.view(-1)[flat.reshape(-1)] = material.repeat_interleave(flat[0].numel())
        return out

    def _check_actions(self, actions: torch.Tensor) -> torch.Tensor:
        if not isinstance(actions, torch.Tensor):
            actions = torch.as_tensor(actions)
        expected = (self.num_envs, self.action_dim)
        if tuple(actions.shape) != expected:
            raise ValueError(
                f"actions must have shape [num_envs, 3 + materials] = {list(expected)}, got {list(actions.shape)}"
            )
        if not actions.is_floating_point():
            raise ValueError(f"actions must be a floating-point tensor, got {actions.dtype}")
        actions = actions.to(self.device)
        if torch.isnan(actions).any():
            raise ValueError("actions must not contain NaN")
        return actions

    # ----------------------------------------------------------------------------------------------- checkpoint
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume mid-episode bit for bit: the grids (per environment, so under ``per_env``:
        a data-parallel checkpoint concatenates them over ranks), the step counter and the configuration."""
        return {
            "per_env": {"grids": self.grids.clone()},
            "t": self.t,
            "seed": self.seed,
            "config": self._config(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; the configuration must match this environment's."""
        config = state.get("config")
        if config != self._config():
            raise ValueError(f"state config {config} does not match this environment's {self._config()}")
        grids = state["per_env"]["grids"]
        check_grids(grids, self.materials, name="state['per_env']['grids']")
        if tuple(grids.shape) != (self.num_envs, *self.observation_shape):
            raise ValueError(
                f"state['per_env']['grids'] must have shape {[self.num_envs, *self.observation_shape]}, got {list(grids.shape)}"
            )
        t = int(state["t"])
        if not 0 <= t < self.steps:
            raise ValueError(f"state['t'] must be in 0 … {self.steps - 1}, got {t}")
        self.grids = grids.to(self.device).clone(memory_format=torch.contiguous_format)
        self.t = t
        self.seed = state.get("seed")

    def _config(self) -> dict[str, Any]:
        """What must match for a state to load (the env count is the grids' first dimension)."""
        return {
            "resolution": self.resolution,
            "materials": self.materials,
            "steps": self.steps,
            "bundle_size": self.bundle_size,
            "action_bound": self.action_bound,
            **({"mirror_y": True} if self.mirror_y else {}),  # absent when off: older states still load
        }

    def __repr__(self) -> str:
        cfg = ", ".join(f"{k}={v}" for k, v in {"num_envs": self.num_envs, **self._config()}.items())
        return f"DesignEnv({cfg}, task={type(self.task).__name__}, device={self.device})"


def _check_design(num_envs: int, design: EnvConfig, materials: int) -> None:
    """Refuse a design env's sizes that are not what :class:`DesignEnv` documents, naming the first wrong one."""
    resolution, bundle_size = design.resolution, design.bundle_size
    _check_int("num_envs", num_envs, "a positive integer")
    _check_int("resolution", resolution, "a positive even integer")
    if resolution % 2:
        raise ValueError(f"resolution must be a positive even integer, got {resolution}")
    _check_int("materials", materials, "an integer >= 2", minimum=2)
    if materials > 256:
        raise ValueError(f"materials must be <= 256 (grids are uint8), got {materials}")
    _check_int("steps", design.steps, "a positive integer")
    _check_int("bundle_size", bundle_size, f"a positive even integer <= resolution ({resolution})")
    if bundle_size % 2 or bundle_size > resolution:
        raise ValueError(
            f"bundle_size must be a positive even integer <= resolution ({resolution}), got {bundle_size}"
        )
    if not design.action_bound > 0:
        raise ValueError(f"action_bound must be > 0, got {design.action_bound}")
    if not isinstance(design.mirror_y, bool):
        raise ValueError(f"mirror_y must be true or false, got {design.mirror_y!r}")


def _check_int(name: str, value: Any, allowed: str, minimum: int = 1) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
