"""Playing controllers on bodies: one episode of several controllers at once, each on its own block of one
``ControlEnv``'s rows, with one noise draw a step shared by every group (common random numbers), and the hand-set
travelling wave as a controller. What ``freeform-control`` and the lab's figure commands play bodies with.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

from freeform.agents.networks.controller_heads import DEFAULT_WAVE, HandSetWave
from freeform.agents.networks.controllers import ContextConvController, controller_observe, controller_step
from freeform.envs.control import ControlEnv
from freeform.envs.response import RESPONSE_CHANNELS

SENSED = ("rel_x", "rel_y", "rel_z", "vel_x", "vel_y", "vel_z", "strain", "contact", *RESPONSE_CHANNELS)
"""The observation's sensed channels: zeroed, a controller has only the body's shape, the task and the clock."""


def hand_set_wave(env: ControlEnv, controller: torch.nn.Module, wave: HandSetWave | None) -> torch.nn.Module:
    """An untrained wave-head context controller for ``env`` (whose actions are strokes): its mean command is the
    hand-set travelling wave — ``wave``, else the controller's own wave, else the default."""
    own = getattr(controller, "wave", None)
    start = wave or (HandSetWave(own["k"], own.get("amplitude", 1.0)) if own else DEFAULT_WAVE)
    net = ContextConvController.for_env(env, head="wave", wave=start).eval()
    with torch.no_grad():  # (the learnt parts at zero: the wave exactly, not the wave plus an init's small noise)
        for layer in (net.actor, net.wave_k):
            layer.weight.zero_()
            layer.bias.zero_()
    return net


class Played(NamedTuple):
    """What :func:`play` returns: each group's return ``[G, rows]``, the return after each decision
    ``[steps, G, rows]`` (the last equals ``returns``), the last observation and the episode's headings."""

    returns: np.ndarray
    after: np.ndarray
    last_obs: torch.Tensor
    heading: np.ndarray


def play(env: ControlEnv, groups: list[tuple], steps: int, seed: int) -> Played:
    """One episode of every group ``(name, net, sensed channels zeroed, stochastic)`` on its block of ``env``'s
    rows (block g is rows ``g·R/G … (g+1)·R/G``)."""
    sensed = [env.channels.index(c) for c in SENSED if c in env.channels]

    def view(obs: torch.Tensor, zeroed: bool) -> torch.Tensor:
        if not zeroed:
            return obs
        obs = obs.clone()
        obs[:, sensed] = 0.0
        return obs

    generator = torch.Generator().manual_seed(seed)
    obs, total = env.reset(), torch.zeros(env.num_envs, dtype=torch.float64)
    states: list = [None] * len(groups)  # (a recurrent controller's, per group, carried through the episode)
    after = []
    for _ in range(steps):
        heading = env.heading.copy()  # (the episode's; the env draws the next episode's at its end)
        # One draw a step for every group (common random numbers): a stochastic group's episode is the same whichever
        # other groups run beside it, and stochastic groups share the noise, so their paired differences carry less of it.
        noise = torch.randn((env.num_envs // len(groups), env.action_dim), generator=generator)
        actions = []
        for g, ((_, net, zeroed, stochastic), part) in enumerate(zip(groups, obs.chunk(len(groups)), strict=True)):
            outputs, states[g] = controller_step(net, view(part, zeroed), states[g])
            params = outputs[:3]
            actions.append(net.distribution.sample(params, noise) if stochastic else net.distribution.mode(params))
        obs, reward, _, _ = env.step(torch.cat(actions))
        for g, ((_, net, _, _), earned) in enumerate(zip(groups, reward.chunk(len(groups)), strict=True)):
            states[g] = controller_observe(net, states[g], earned)  # (a controller that reads rewards: a gate)
        total += reward.double()
        after.append(total.numpy().reshape(len(groups), -1).copy())
    return Played(after[-1], np.stack(after), obs, heading)


class BankOnBodies(torch.nn.Module):
    """A bank of per-body controllers (``freeform.agents.distill.teachers.TeacherBank``) acting on an env's rows, built for
    the env's box ``box``: row r is driven by teacher ``teacher[r]`` (int64 ``[rows]``)."""

    def __init__(self, bank: Any, teacher: torch.Tensor, box: tuple[int, ...]) -> None:
        super().__init__()
        from freeform.agents.distill.teachers import TeacherBank

        k = bank.init_kwargs  # (built for the evaluation's box: the kinds that fit any box)
        self.bank = TeacherBank(**{**k, "controller": {**k["controller"], "box": tuple(box)}})
        self.bank.load_state_dict(bank.state_dict())
        self.teacher, self.distribution = teacher, self.bank.distribution

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.bank({"teacher": self.teacher, "policy": obs}))


@torch.no_grad()
def own_moves(bank: Any, env: ControlEnv, seed: int = 0, episodes: int = 1) -> np.ndarray:
    """Each row's move ``[rows]`` in one episode of ``env`` (``episodes`` rows a body, as ``block_env`` lays them
    out), the rows of body i driven by the bank's controller i by its mean command: per-body controllers on their
    own bodies."""
    if env.num_envs % episodes:
        raise ValueError(f"{env.num_envs} rows are not {episodes} episodes a body")
    member = torch.arange(env.num_envs // episodes).repeat_interleave(episodes)
    own = BankOnBodies(bank, member, tuple(env.box)).eval()
    return play(env, [("own", own, False, False)], env.control.steps, seed).returns[0]


__all__ = ["SENSED", "BankOnBodies", "Played", "hand_set_wave", "own_moves", "play"]
