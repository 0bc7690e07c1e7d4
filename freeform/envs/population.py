"""A control env over a stream of bodies (issue 42): one controller meets bodies it has not seen every few episodes,
so it cannot learn one body's gait and must learn what moves bodies in general.

The bodies come in *cohorts* of ``num_envs`` (a cohort is what one episode controls, one body per environment).
Cohort ``c`` is a pure function of ``(body_seed, c)`` (:func:`design_cohort`: bodies an untrained design policy
builds, the design env's sizes), so the whole stream is reproducible and a checkpoint needs only the episode count.

Which cohorts an episode may draw from — the *pool* — slides along the stream: at episode ``e`` it holds cohorts
``g … g + pool − 1`` with ``g = e // refresh_every`` (``refresh_every = 0``: never slides, a fixed population of
``pool · num_envs`` bodies), and episode ``e`` plays cohort ``g + u`` with ``u`` drawn from
``default_rng([seed, e])``. Each cohort is settled once (``control.burn_in``, the settling every control episode
starts from) and its state kept (``Engine.snapshot``), so a body that is drawn again restores that state instead of
settling anew: a new cohort costs one settle, a reused one nothing. Cohorts that left the pool are forgotten.

With ``copies = m > 1`` a cohort holds ``num_envs / m`` bodies, each controlled by ``m`` environments side by side
from the same settled state (and, with random headings, the same heading): :attr:`PopulationControlEnv.reward_groups`
names each environment's body, so that PPO's ``group_baseline`` can judge a copy's rewards against its siblings'
(what the copies differ in is the policy's noise alone) instead of against other bodies, whose gaits differ by more
than any correction.

Everything else — observations, actions, rewards, the episode, bandwidth and residual control — is
:class:`~freeform.envs.control.ControlEnv`'s, on a box fixed for the whole stream (the design grid's ρ³ unless
given: every body of the design env fits it), so the rollout's shapes never change.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from freeform.envs.control import ControlConfig, ControlEnv, arch_for, same_config
from freeform.envs.untrained import DesignBodies, untrained_design_bodies
from freeform.sim import SimConfig, Simulator


def cohort_at(episode: int, pool: int, refresh_every: int, seed: int) -> int:
    """The cohort episode ``episode`` of a stream with this ``pool``, ``refresh_every`` and ``seed`` plays (module
    docstring): what :meth:`PopulationControlEnv.cohort_at` answers, for a stream not built."""
    first = episode // refresh_every if refresh_every else 0
    return first + int(np.random.default_rng([seed, episode, 1]).integers(pool))


def robot_seconds(episodes: int, num_envs: int, control: Any, seed: int) -> float:
    """The simulated robot-seconds of ``episodes`` episodes of a stream of ``num_envs`` environments (``control``:
    a run's ``control`` section, with ``burn_in``, ``duration``, ``pool``, ``refresh_every``): every environment's
    control window each episode, and one settle (``burn_in``) of every environment of each cohort played — cohort 0
    (built with the env) and the next episode's (the last step's reset settles it) included; a reused cohort
    restores its settled state for nothing."""
    played = {0} | {cohort_at(e, control.pool, control.refresh_every, seed) for e in range(episodes + 1)}
    return episodes * num_envs * control.duration + len(played) * num_envs * control.burn_in


def design_cohort(sizes: DesignBodies, n: int, body_seed: int, cohort: int) -> torch.Tensor:
    """Cohort ``cohort`` of the stream ``body_seed``: ``n`` non-empty bodies, uint8 ``[n, ρ, ρ, ρ]`` (each the
    largest component an untrained design policy builds, or ``sizes.designer``'s bodies; the rare empty design is
    replaced by the next draw)."""
    found: list[torch.Tensor] = []
    draw = 0
    while sum(len(g) for g in found) < n:
        seed = int(np.random.SeedSequence([body_seed, cohort, draw]).generate_state(1)[0])
        if sizes.designer is not None:
            grids = sizes.designer(n + n // 8 + 1, sizes, seed)
        else:
            grids = untrained_design_bodies(n + n // 8 + 1, sizes.resolution, sizes.materials, sizes.steps,
                                            sizes.bundle_size, seed)
        found.append(grids[(grids.flatten(1) > 0).any(dim=1)])
        draw += 1
        if draw > 100:
            raise RuntimeError(f"design_cohort: fewer than {n} non-empty bodies in {draw} draws of {sizes}")
    return torch.cat(found)[:n].contiguous()


@dataclass(frozen=True)
class Stream:
    """The stream of cohorts a :class:`PopulationControlEnv` plays (module docstring).

    total, copies: environments of each cohort, and environments per body (``total`` holds whole groups of copies).
    pool, refresh_every: cohorts an episode may draw from, and episodes between two steps of the pool along the
        stream (0: the pool never moves).
    body_seed: which stream (:func:`design_cohort`).
    box: the control box of every cohort (None: the design grid's ρ³, which every body of the design env fits).
    """

    total: int
    pool: int = 4
    refresh_every: int = 1
    body_seed: int = 0
    copies: int = 1
    box: tuple[int, int, int] | None = None


class PopulationControlEnv:
    """``ControlEnv`` episodes over cohorts of fresh bodies (module docstring): a :class:`freeform.envs.VecEnv`
    with the control env's observations and actions on a fixed ``box``.

    sizes, stream: the bodies (:func:`design_cohort`) and the stream of cohorts (:class:`Stream`).
    envs = (lo, hi): this env's environments of each cohort of ``stream.total`` (a data-parallel rank holds a slice
        of every cohort), whole groups of copies.
    sim, control, seed, device: as :class:`ControlEnv` (episode e's headings and cohort are drawn from
        ``default_rng([seed, e])``).
    """

    def __init__(self, sizes: DesignBodies, stream: Stream, sim: SimConfig | None = None,
                 control: ControlConfig | None = None, seed: int = 0, device: str | torch.device = "cpu",
                 envs: tuple[int, int] | None = None) -> None:
        total, copies, pool, refresh_every = stream.total, stream.copies, stream.pool, stream.refresh_every
        lo, hi = envs if envs is not None else (0, total)
        if not (isinstance(total, int) and 0 <= lo < hi <= total):
            raise ValueError(f"envs must be (lo, hi) with 0 <= lo < hi <= total = {total!r}, got {envs!r}")
        if not (isinstance(copies, int) and copies >= 1):
            raise ValueError(f"copies must be an int >= 1 (environments per body), got {copies!r}")
        if total % copies or lo % copies or hi % copies:
            raise ValueError(f"copies = {copies} must divide the cohort's {total} environments and this process's "
                             f"slice {lo}..{hi} (each body's copies side by side in one process)")
        if not (isinstance(pool, int) and pool >= 1):
            raise ValueError(f"pool must be an int >= 1 (cohorts of bodies an episode draws from), got {pool!r}")
        if not (isinstance(refresh_every, int) and refresh_every >= 0):
            raise ValueError(f"refresh_every must be an int >= 0 (episodes; 0: a fixed pool), got {refresh_every!r}")
        self.sizes, self.total, self.envs, self.copies = sizes, total, (lo, hi), copies
        self.pool, self.refresh_every, self.body_seed = pool, refresh_every, int(stream.body_seed)
        self.control, self._sim = control or ControlConfig(), sim or SimConfig()
        self.control.validate()
        self.sim_config = ControlEnv.simulation(self._sim, self.control)
        self.seed, self.device = int(seed), torch.device(device)
        self.simulator = Simulator(self.sim_config, arch=arch_for(self.device))
        self.num_envs = hi - lo
        self.box = tuple(int(b) for b in stream.box) if stream.box is not None else (sizes.resolution,) * 3
        self.reward_groups = torch.arange(lo, hi, device=self.device) // copies - lo // copies
        """Each environment's body within this process, int64 ``[num_envs]``: environments of one group are copies."""
        self._cohorts: dict[int, ControlEnv] = {}
        self.episode = -1
        self.current = self._cohort(0)  # (its shapes are every cohort's: the same box and channels)

    def __getattr__(self, name: str) -> Any:
        """Everything else is the playing cohort's ``ControlEnv``'s — its shapes (``observation_shape``,
        ``action_dim``, ``action_distribution``, … the same in every cohort: one box, one ``ControlConfig``), its
        ``action_mask``, ``heading`` — read from it, never copied."""
        current = self.__dict__.get("current")
        if current is None or name.startswith("__"):
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(current, name)

    # ------------------------------------------------------------------ the stream
    def cohort_at(self, episode: int) -> int:
        """The cohort episode ``episode`` plays (module docstring)."""
        return cohort_at(episode, self.pool, self.refresh_every, self.seed)

    def _cohort(self, c: int) -> ControlEnv:
        if c not in self._cohorts:
            lo, hi = self.envs
            m = self.copies
            grids = design_cohort(self.sizes, self.total // m, self.body_seed, c).repeat_interleave(m, 0)[lo:hi]
            draws = np.arange(lo, hi) // m if m > 1 else lo  # (copies share their heading's draw)
            self._cohorts[c] = ControlEnv(grids, sim=self._sim, control=self.control, seed=self.seed,
                                          device=self.device, first_env=draws, box=self.box, simulator=self.simulator)
        return self._cohorts[c]

    @property
    def grids(self) -> torch.Tensor:
        """The bodies of the episode now playing, uint8 ``[num_envs, ρ, ρ, ρ]``."""
        return self.current.grids

    # ------------------------------------------------------------------ the VecEnv
    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Start the next episode: its cohort (settled once, restored after), its headings."""
        if seed is not None:
            self.seed, self.episode = int(seed), -1
            for env in self._cohorts.values():
                env.seed = self.seed
        self.episode += 1
        c = self.cohort_at(self.episode)
        first = self.episode // self.refresh_every if self.refresh_every else 0
        for old in [k for k in self._cohorts if k < first and k != c]:  # (left the pool: never drawn again)
            del self._cohorts[old]
        self.current = self._cohort(c)
        return self.current.reset(episode=self.episode)

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """One control period of the episode's cohort; at the episode's end the next episode starts (another
        cohort, perhaps) and ``info`` describes the finished one, as :meth:`ControlEnv.step`."""
        obs, reward, done, info = self.current.step(actions)
        if self.current.t == 0:  # (the cohort's env reset itself: start the stream's next episode instead)
            obs = self.reset()
        return obs, reward, done, info

    def record(self, act: Any, robot: int = 0, every: int | None = None) -> tuple[Any, np.ndarray, float]:
        """One episode of robot ``robot`` of the current cohort under ``act`` (:meth:`ControlEnv.record`)."""
        return self.current.record(act, robot, every)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The stream's position (between episodes): its bodies follow from it, and are checked on load."""
        if self.current.t != 0:
            raise ValueError(f"a PopulationControlEnv saves its state between episodes, and this one is "
                             f"{self.current.t} control steps into episode {self.episode}")
        return {"per_env": {"grids": self.current.grids.clone()}, "episode": self.episode, "seed": self.seed,
                "config": self._config()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict`: the same stream, at the start of the saved episode."""
        if not same_config(state.get("config"), self._config()):
            raise ValueError(f"state config {state.get('config')} does not match this environment's {self._config()}")
        self.seed, self.episode = int(state["seed"]), int(state["episode"]) - 1
        for env in self._cohorts.values():
            env.seed = self.seed
        self.reset()
        grids = torch.as_tensor(state["per_env"]["grids"]).cpu()
        if not torch.equal(grids, self.current.grids):
            raise ValueError("the state's bodies (per_env.grids) are not this stream's at its episode: a population "
                             "run resumes with the body_seed and design sizes it was trained with")

    def _config(self) -> dict[str, Any]:
        return {"control": vars(self.control).copy(), "box": list(self.box), "sizes": self.sizes.config(),
                "total": self.total, **({"copies": self.copies} if self.copies > 1 else {}), "pool": self.pool, "refresh_every": self.refresh_every,
                "body_seed": self.body_seed}


__all__ = ["DesignBodies", "PopulationControlEnv", "Stream", "design_cohort"]
