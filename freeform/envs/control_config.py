"""A control episode's timing and task (``ControlConfig``: ``control.*`` of a run, the env part of
``freeform.config.ControlRunConfig``), apart from the env that runs it (:mod:`freeform.envs.control`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

HEADINGS = ("fixed", "random", "any")
FRAMES = ("world", "heading")


@dataclass
class ControlConfig:
    """An episode's timing and the task.

    period: simulated seconds per control step. 0.0125 s = 1/20 of the default actuation period (0.25 s): 20
        decisions per stroke of the open-loop gait it replaces, ≈ 100 simulator steps at the default dt (1.2e-4 s).
    duration: simulated seconds of control per episode (``round(duration / period)`` steps).
    burn_in: seconds of settling before the controller acts (commands 0: no actuation, or under ``residual`` the
        open-loop gait).
    headings: "fixed" (+x: locomotion) | "random" (one uniform heading per robot and episode: steering) | "any"
        (the distance moved in the plane, whichever way: the paper's locomotion reward; no heading observed).
    command_rate: the most what a muscle receives may change per simulated second (None: any change, at once —
        Voxelyze's actuation sets the rest size instantly). A muscle's bandwidth: 2π·f_max for full-amplitude swings
        up to f_max Hz (the open-loop sine's 4 Hz: ≈ 25.1 /s, so 26 lets that gait through untouched); at each control
        step what a voxel receives — its command, or under ``residual`` its sine plus its correction, clipped to
        [−1, 1] — moves towards what the action asks by at most ``command_rate · period`` (held at the control
        steps' ends; with ``ramp`` the received value moves linearly between them, up to the sine's own curvature).
    residual: actions (in [−2, 2]) are corrections added to the open-loop gait, each actuated voxel's sine of its
        material's phase, computed at every simulator step (``SimConfig(actuation="residual")``), and the
        observation carries that sine (``RESIDUAL_CHANNELS``); zero actions are the open-loop gait from t = 0, burn-in
        included, bit for bit. False: an action is the command itself, in [−1, 1] (zero: no actuation).
    ramp: each step's command moves linearly from the last one to the new one over the control period (a
        first-order hold: ``Engine.set_commands(ramp=period)``) instead of jumping at the period's start — Voxelyze
        sets a voxel's rest size at once, so a jump of the command is a kick.
    stroke_periods: 0 — an action is one control period's commands. n >= 1 — an action is a *stroke*, held for n
        control periods: each cell's pair (a, b), and what the voxel receives at each of those periods is
        a·sin θ + b·cos θ, θ = 2π(t/T + φ) the phase of its own open-loop sine at the period's middle (φ its
        material's phase): under ``residual`` control (0, 0) is the open-loop gait, b shifts its phase and a scales
        it. The action is ``[N, 2·Bx·By·Bz]`` (every a, then every b); an episode is ``duration / (n·period)``
        decisions, each of whose exploration noise acts over a whole stroke instead of one period.
    frame: the frame the observation's planar vectors are given in. "world" — the ground's x and y, the heading
        in its own channels. "heading" — turned about z by minus the robot's heading, so x lies along it (the
        heading channels 0: the task is always +x): the positions from the centre of mass, velocities and
        responses, and a privileged critic's displacement and orientation. The ground is the same every way, so a
        body asked to go along θ is, in this frame, a body turned by −θ asked to go along +x: what steering asks
        of a controller becomes one task seen in every orientation, and a voxel's place along the heading — what a
        travelling wave's phase follows — is one channel instead of a product of two (``docs/control.md``,
        "Steering"). Under ``headings`` "fixed" and "any" (heading 0) the two frames agree, heading channels apart.
    privileged_critic: the observation becomes the groups ``{"policy": the cells' channels, "critic": [N, 10]}``
        (``freeform.agents.networks.observation_groups``): the critic also reads what the sensors lack (``CRITIC_STATE``) —
        each body's displacement since the episode's start (voxel lengths; under ``headings="any"`` its reward is
        the growth of that distance), its orientation, and the episode's time left — and the actor does not.
    """

    period: float = 0.0125
    duration: float = 2.0
    burn_in: float = 0.25
    headings: str = "fixed"
    command_rate: float | None = None
    residual: bool = False
    ramp: bool = False
    stroke_periods: int = 0
    privileged_critic: bool = False
    response: bool = False
    frame: str = "world"

    @property
    def periods_per_step(self) -> int:
        """Control periods one action lasts (``stroke_periods``, or 1)."""
        return max(1, self.stroke_periods)

    @property
    def decision_seconds(self) -> float:
        """Simulated seconds one action lasts (``periods_per_step`` control periods)."""
        return self.period * self.periods_per_step

    @property
    def steps(self) -> int:
        """Decisions (env steps) per episode."""
        return max(1, round(self.duration / self.decision_seconds))

    def validate(self, key: str = "control") -> None:
        for name in ("period", "duration"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{key}.{name} must be > 0 (seconds), got {getattr(self, name)!r}")
        if not self.burn_in >= 0:
            raise ValueError(f"{key}.burn_in must be >= 0 (seconds), got {self.burn_in!r}")
        if self.headings not in HEADINGS:
            raise ValueError(f"{key}.headings must be one of {HEADINGS}, got {self.headings!r}")
        if self.frame not in FRAMES:
            raise ValueError(f"{key}.frame must be one of {FRAMES}, got {self.frame!r}")
        if self.command_rate is not None and not self.command_rate > 0:
            raise ValueError(f"{key}.command_rate must be None or > 0 (per second), got {self.command_rate!r}")
        for name in ("residual", "ramp", "privileged_critic", "response"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{key}.{name} must be true or false, got {getattr(self, name)!r}")
        if not (isinstance(self.stroke_periods, int) and not isinstance(self.stroke_periods, bool)
                and self.stroke_periods >= 0):
            raise ValueError(f"{key}.stroke_periods must be an int >= 0 (0: an action is one period's commands), "
                             f"got {self.stroke_periods!r}")


#: The fields that fix what a controller reads and writes — its observation's channels (``residual``'s open-loop
#: channel, ``response``'s six, the heading channels and the planar vectors' ``frame``), its action's layout
#: (``stroke_periods``) — and the task its weights learnt (``headings``). A controller trained under other values of
#: any of them reads or writes another layout than this env's (a shape error deep inside, or channels read as
#: others), or was trained for another task.
INTERFACE = ("headings", "frame", "residual", "response", "stroke_periods")


def differing_fields(theirs: Any, mine: Any, fields: tuple[str, ...], bank: bool = False) -> list[str]:
    """The ``fields`` on which ``theirs`` and ``mine`` (``ControlConfig``s, or runs' ``control`` sections) differ.
    ``bank``: ``theirs`` is a teacher bank's, which reads its own channels, the first ones — so the response channels
    that ``mine`` adds after them (``response``) are no difference."""
    return [k for k in fields if getattr(theirs, k) != getattr(mine, k)
            and not (bank and k == "response" and mine.response)]


def described_differences(theirs: Any, mine: ControlConfig, whose: str, fields: tuple[str, ...] = INTERFACE,
                          bank: bool = False) -> list[str]:
    """The ``fields`` (by default :data:`INTERFACE`) on which ``theirs`` (another run's ``control`` section, named
    ``whose``, e.g. "the teacher run"; ``bank``: :func:`differing_fields`) differs from ``mine``, each as
    ``"control.<field>: <theirs> in <whose>, <mine> here"`` — the one wording of a refusal of another run's
    ``control`` settings (the distillation's teacher check, the evaluation's ``--per-body-run``); empty when they
    agree."""
    return [f"control.{k}: {getattr(theirs, k)!r} in {whose}, {getattr(mine, k)!r} here"
            for k in differing_fields(theirs, mine, fields, bank)]


def same_config(saved: Any, mine: dict[str, Any]) -> bool:
    """Whether an env's saved config (a checkpoint's ``{"control": vars(ControlConfig), ...}``) is ``mine``; a
    control field it lacks — saved before the field existed — counts as that field's default, so older runs resume."""
    if not (isinstance(saved, dict) and isinstance(saved.get("control"), dict)):
        return False
    return {**saved, "control": {**vars(ControlConfig()), **saved["control"]}} == mine


__all__ = ["FRAMES", "HEADINGS", "INTERFACE", "ControlConfig", "described_differences", "differing_fields", "same_config"]
