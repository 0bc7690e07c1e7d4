"""A controller that chooses among experts by trial within one episode: :class:`TrialGate`.

``freeform-control fit`` tries every candidate for a whole episode of its own and keeps the best — K episodes a body.
A trial gate does it inside one: it plays expert 0 for ``trial`` decisions, then expert 1, … expert K−1, summing the
reward each earned in its window, and then commits to the expert whose window earned most (a tie goes to the earlier)
for the rest of the episode. It is one ``controller.pt`` (``freeform.agents.controller_file``: kind ``gated``) that
``evaluate``, ``watch`` and ``fit`` play like any controller.

It reads the reward of each step (what RL² policies read besides the observation): ``observe(state, reward)``, which
every play loop calls after every step (``freeform.agents.networks.controllers.controller_observe``). A controller on
a robot gets it from its odometry. Its state is ``[N, 2 + K]``: decisions taken this episode, the expert that acted
last, and each expert's summed reward.

A gate is made of trained controllers and never trained itself, so it is not a kind of
:data:`~freeform.agents.networks.controllers.CONTROLLERS` (what ``control.controller`` builds) but of
:data:`PLAYABLE`, every kind a ``controller.pt`` holds.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn as nn

from freeform.agents.networks import rebuild
from freeform.agents.networks.controllers import CONTROLLERS, controller_kind
from freeform.agents.networks.recurrent import RecurrentPolicy, State

DECISIONS, ACTED = 0, 1
"""Columns of a gate's state; the experts' summed rewards follow."""


class TrialGate(nn.Module):
    """``experts`` (feed-forward controllers of one action distribution), each tried for ``trial`` decisions in
    turn, then the best of them by its window's reward (module docstring). ``forward(obs [1, N, ...], state,
    episode_start [1, N])`` → ``(mean, log σ, mask, value, state)``, each output ``[1, N, ...]`` (a recurrent policy
    of one step; a row whose episode starts is reset)."""

    fits_any_box = False  # (a class's defaults; a gate's own are its experts')
    padding_invariant = False

    def __init__(self, experts: list[dict[str, Any]], trial: int) -> None:
        super().__init__()
        if not experts:
            raise ValueError("a trial gate needs at least one expert")
        if not (isinstance(trial, int) and trial >= 1):
            raise ValueError(f"a trial lasts a whole number of decisions >= 1, got {trial!r}")
        for e in experts:
            if e["kind"] not in CONTROLLERS:
                raise ValueError(f"an expert's kind must be one of {list(CONTROLLERS)}, got {e['kind']!r}")
            if issubclass(CONTROLLERS[e["kind"]], RecurrentPolicy):
                raise ValueError(f"expert kind {e['kind']!r} is recurrent; a gate plays feed-forward experts")
        self.experts = nn.ModuleList(rebuild(CONTROLLERS[e["kind"]], e["init_kwargs"]) for e in experts)
        self.trial = trial
        self.init_kwargs = {"experts": [{"kind": e["kind"], "init_kwargs": dict(e["init_kwargs"])} for e in experts],
                            "trial": trial, "box": tuple(experts[0]["init_kwargs"]["box"])}
        if len({e.distribution for e in self.experts}) != 1 or len({tuple(e.box) for e in self.experts}) != 1:
            raise ValueError("a gate's experts must act alike — one action distribution, one box — and got "
                             f"{[(type(e.distribution).__name__, getattr(e.distribution, 'dim', None), tuple(e.box)) for e in self.experts]}")
        self.distribution = self.experts[0].distribution
        self.box = self.init_kwargs["box"]
        self.fits_any_box = all(e.fits_any_box for e in self.experts)
        self.padding_invariant = all(e.padding_invariant for e in self.experts)

    @classmethod
    def from_controllers(cls, controllers: list[nn.Module], trial: int) -> TrialGate:
        """A gate over these controllers (their weights copied), each tried for ``trial`` decisions."""
        gate = cls([{"kind": controller_kind(c), "init_kwargs": c.init_kwargs} for c in controllers], trial)
        for mine, theirs in zip(gate.experts, controllers, strict=True):
            mine.load_state_dict(theirs.state_dict())
        return gate

    @classmethod
    def from_init_kwargs(cls, kwargs: dict[str, Any]) -> TrialGate:
        """Rebuilt from a file's ``init_kwargs``; a ``box`` there (a box other than the one saved: ``read_controller``)
        is every expert's."""
        box = tuple(kwargs["box"])
        experts = [{"kind": e["kind"], "init_kwargs": {**e["init_kwargs"], "box": box}} for e in kwargs["experts"]]
        return cls(experts, int(kwargs["trial"]))

    @property
    def trials_end(self) -> int:
        """The decision at which the gate commits: after every expert's window."""
        return self.trial * len(self.experts)

    def initial_state(self, num_envs: int) -> State:
        return (torch.zeros(num_envs, 2 + len(self.experts), device=self._device()),)

    def _device(self) -> torch.device:
        return next(self.parameters()).device

    def chosen(self, state: State) -> torch.Tensor:
        """The expert each row plays at its next decision ``[N]`` int64: its window's expert during the trials, then
        the one whose window earned most."""
        (s,) = state
        t = s[:, DECISIONS].long()
        best = s[:, 2:].argmax(1)  # (ties: the first, the earlier expert)
        return torch.where(t < self.trials_end, torch.div(t, self.trial, rounding_mode="floor"), best)

    def forward(self, obs: torch.Tensor, state: State, episode_start: torch.Tensor) -> tuple[torch.Tensor, ...]:
        (s,) = state
        s = torch.where(episode_start[0][:, None], torch.zeros_like(s), s)
        who = self.chosen((s,))
        outputs = [e(obs[0]) for e in self.experts]  # (K passes over the batch: experts are small, K a handful)
        picked = []
        for j in range(len(outputs[0])):
            stacked = torch.stack([o[j] for o in outputs])  # [K, N, ...]
            index = who.view(1, -1, *([1] * (stacked.dim() - 2))).expand(1, *stacked.shape[1:])
            picked.append(stacked.gather(0, index)[0][None])
        s = s.clone()
        s[:, ACTED] = who.to(s.dtype)
        s[:, DECISIONS] += 1
        return (*picked, (s,))

    def observe(self, state: State, reward: torch.Tensor) -> State:
        """``state`` after a step that earned ``reward`` ``[N]``: added to the acting expert's sum while trials last."""
        (s,) = state
        s = s.clone()
        trying = (s[:, DECISIONS] <= self.trials_end).to(s.dtype)  # (the decision just played was a trial's)
        s.scatter_add_(1, 2 + s[:, ACTED].long()[:, None], (reward.to(s) * trying)[:, None])
        return (s,)


PLAYABLE: dict[str, type[nn.Module]] = {**CONTROLLERS, "gated": TrialGate}
"""Every kind a ``controller.pt`` may hold (``freeform.agents.controller_file``): the trainable ones, and the gate."""


def playable_kind(controller: nn.Module) -> str:
    """The name :data:`PLAYABLE` gives ``controller``'s class."""
    return "gated" if isinstance(controller, TrialGate) else controller_kind(controller)


__all__ = ["PLAYABLE", "TrialGate", "playable_kind"]
