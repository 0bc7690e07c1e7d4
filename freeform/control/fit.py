"""A controller for each of your bodies: the zoo's controllers tried on it, the best kept, then adapted to it by
PPO — ``freeform-control fit``.

**Trials.** Every candidate (the zoo's :data:`freeform.zoo.TRIED`, the hand-set wave among them) drives every body
by its mean command for one episode, all in one env (a block of rows a candidate); a body's controller is the one
that moved it furthest after the trial's decisions (``--trial SECONDS``; default the whole episode), and its figure
is its whole episode. The mean command is deterministic, so that figure is what ``evaluate`` reports for the body.

**Steering** (candidates that follow a heading drawn each episode, ``headings: random``: the zoo's :data:`STEERING`).
The best of several controllers on one draw of headings is biased upwards on that draw, so choices and figures never
share one: every figure (``mean_command``, the curve) is the mean of ``--episodes`` episodes (episodes 0 … K−1,
``evaluate``'s), and each trial the mean of ``--trial-episodes`` episodes along the headings of the episodes *after*
those (:func:`trial_draws`) — a body's pick and its adaptation are chosen on the trial draws, reported on the
others. The adaptation's recipes are the steering presets' (:data:`STEERING_RECIPES`).

**Adaptation** (``--adapt-epochs E`` > 0, or ``--adapt-seconds S``: as many epochs as fit in S seconds a body,
trials included). Each body's best candidate of a kind the adaptation trains
(:data:`RECIPES`: the zoo's students, and context controllers such as the population controller and per-body
controllers of other bodies; :func:`recipe_of` — a candidate of another kind is tried and kept where it wins, not
adapted) is trained on that body alone for E epochs of PPO by its kind's recipe — the bodies of one recipe at once,
as one bank of per-body controllers (``freeform.agents.distill.teachers.TeacherBank``, each body ``--copies``
environments with a leave-one-out baseline among them; two recipes' banks take their epochs in turn), by the
preset's learning rate and batch (``conf/experiment/``; ``--set agent.lr=1e-3`` changes every recipe's). Each body
then keeps whichever of the adapted and the chosen controller (its best trial of all) moves it further by its mean
command. With ``--curve-every K`` the bodies are measured every K epochs (and before the first and after the last)
into ``adaptation.csv``: what a body gains for the seconds it costs (the bodies' mean; ``adaptation_bodies.csv``
body by body).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from freeform.control.evaluate import EPISODES, block_env, episode_of, figure_episodes
from freeform.control.play import own_moves, play
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.envs.control_config import described_differences
from freeform.sim import SimConfig

EPISODE = tuple(f.name for f in fields(ControlConfig))
"""Every field of an episode: what two controllers tried side by side, or a controller and its adaptation, share."""

FIT_SETS = {"control.bodies": "from the bodies", "control.teachers": "one controller a body",
            "control.controller_init": "each body starts from its best candidate of the adaptation's kind",
            "env.num_envs": "give --copies", "trainer.epochs": "give --adapt-epochs", "seed": "give --seed",
            "agent.seed": "give --seed", "experiment": "the recipes are fit's (RECIPES)",
            "agent.eval_every": "fit measures the adaptation itself: give --curve-every",
            "trainer.plateau_on": "fit's adaptation runs its epochs, it reads no plateau"}
"""The adaptation's keys that ``fit`` sets itself (and how a user sets them), which ``--set`` may not name."""

RECIPES = ("control_adapt_cpu", "control_teachers_cpu")
"""The adaptation's recipes (``conf/experiment/``), each the one for the kind of controller it trains: the zoo's
students (voxel-token attention, 32 wide; lr 3e-4, at which PPO does not first undo the distillation) and context
controllers (16 wide: the population controller, and per-body controllers, a library's; the per-body teachers'
recipe, lr 1e-3). A body's best candidate is adapted by the first recipe that trains its kind."""

STEERING_RECIPES = ("control_adapt_steering_cpu", "control_teachers_steering_cpu")
"""The same two for steering candidates (random headings): the steering student's and the steering teachers'."""

TRIAL_EPISODES = 4
"""Episodes a steering trial averages (headings random; a heading task that draws nothing plays one): the heading
changes a body's move several-fold, so one draw would choose by the heading more than by the controller."""

DEFAULT_ADAPT_EPOCHS = 24
"""The adaptation ``fit`` runs unless told otherwise: 24 epochs, about a minute of 2-core time a body (59–72 s on
the held-out bodies; docs/control.md)."""

BUDGET_EPOCHS = 1000
"""The most epochs an adaptation by seconds (``--adapt-seconds``) runs where ``--adapt-epochs`` sets no cap."""


@dataclass(frozen=True)
class Fit:
    """How ``fit`` works: the candidates (zoo names or ``controller.pt`` paths, tried in this order: a tie goes to
    the earlier), the trial's seconds (None: the whole episode), the adaptation's epochs (0: trials alone), its
    environments per body, the presets whose recipes it follows (:data:`RECIPES`), and the seed."""

    candidates: tuple[str, ...]
    trial: float | None = None
    adapt_epochs: int | None = None
    """None: :data:`DEFAULT_ADAPT_EPOCHS`, or :data:`BUDGET_EPOCHS` (a cap) with ``adapt_seconds``."""
    copies: int = 4
    presets: tuple[str, ...] | None = None
    """None: the candidates' task's (:data:`RECIPES`, :data:`STEERING_RECIPES` for random headings)."""
    seed: int = 0
    curve_every: int = 0
    """Measure the bodies every this many adaptation epochs (and at 0 and the last) into ``adaptation.csv``; 0:
    never."""
    settings: tuple[str, ...] = ()
    """Hydra overrides of every recipe (``agent.lr=1e-3``), applied before what fit sets itself (the keys of
    :data:`FIT_SETS`, which they may not name)."""
    adapt_seconds: float | None = None
    """Adapt until a body's share of the wall time since fit began (trials included, the curve's measuring not)
    would pass this many seconds with one more epoch — at least one epoch, at most ``adapt_epochs``; None: every one
    of ``adapt_epochs``."""
    trial_episodes: int | None = None
    """Episodes a trial averages, for candidates along random headings (None: :data:`TRIAL_EPISODES`); other
    heading tasks play every episode alike, and take one."""
    episodes: int | None = None
    """Episodes a figure averages, for candidates along random headings (None: ``evaluate``'s
    :data:`~freeform.control.evaluate.EPISODES`); other heading tasks take one."""

    def __post_init__(self) -> None:
        if self.adapt_epochs is None:  # (frozen: set once, here)
            object.__setattr__(self, "adapt_epochs",
                               DEFAULT_ADAPT_EPOCHS if self.adapt_seconds is None else BUDGET_EPOCHS)
        if self.settings and not self.adapt_epochs:
            raise ValueError(f"--set {' '.join(self.settings)}: changes the adaptation, and --adapt-epochs 0 runs "
                             "none (trials alone have no recipe)")
        for setting in self.settings:
            key, eq, _ = setting.partition("=")
            if key.startswith("~"):
                raise ValueError(f"--set {setting!r}: fit changes the adaptation's keys, it deletes none")
            if not eq or not key.strip("+"):
                raise ValueError(f"--set {setting!r}: give KEY=VALUE, a key of the adaptation's config "
                                 "(agent.lr=1e-3)")
            if (flag := FIT_SETS.get(key.lstrip("+"))) is not None:
                raise ValueError(f"--set {setting!r}: fit sets {key.lstrip('+')} itself ({flag})")
        if self.adapt_epochs < 0:
            raise ValueError(f"--adapt-epochs must be >= 0 (0: trials alone), got {self.adapt_epochs}")
        if self.adapt_seconds is not None and not (np.isfinite(self.adapt_seconds) and self.adapt_seconds > 0
                                                   and self.adapt_epochs):
            raise ValueError(f"--adapt-seconds {self.adapt_seconds}: a number of seconds > 0, with --adapt-epochs > 0 "
                             "(its cap; 0 runs no adaptation)")
        for flag, value in (("--trial-episodes", self.trial_episodes), ("--episodes", self.episodes)):
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{flag} must be a whole number >= 1, got {value!r}")
        if self.curve_every < 0 or (self.curve_every and not self.adapt_epochs):
            raise ValueError(f"--curve-every {self.curve_every}: a whole number of adaptation epochs >= 0 (0: never), "
                             "with --adapt-epochs > 0 (trials alone have no curve)")


def candidate_name(spec: str) -> str:
    """How tables name a candidate: a zoo name as it is, a file by its folder (``runs/mine/controller.pt``: ``mine``),
    a folder by itself."""
    from freeform.zoo import ORDER

    if spec in ORDER:  # (the library's members too: library/d0)
        return spec
    path = Path(spec)
    return path.parent.name if path.suffix == ".pt" and path.parent.name else path.stem if path.suffix else path.name


def episode_differences(saved: Any, control: ControlConfig, sim: SimConfig, first: Path) -> list[str]:
    """Where a saved controller plays another episode than ``control`` (its own along ``control``'s headings: every
    ``ControlConfig`` field named) or moves in another simulator than ``sim`` (``ControlEnv.physics_differences``:
    the schedule and backend may differ) — one string each, empty where it plays the same. ``first``: the
    controller the others are compared with, for the wording."""
    from dataclasses import replace

    differ = described_differences(replace(saved.control, headings=control.headings), control, str(saved.path), EPISODE)
    physics = ControlEnv.physics_differences(saved.sim or SimConfig(), sim, control, str(saved.path), f"in {first}")
    return [*differ, *([physics] if physics else [])]


def read_alike(specs: tuple[str, ...], why: str, box: tuple[int, ...] = (), who: str = "") -> tuple[list, Any, Any]:
    """The controllers ``specs`` (zoo names or paths) read back, built for one box — the smallest holding ``box`` and
    every one's own — and checked to play one episode in one simulator (each difference named, then ``why`` they must;
    ``who`` prefixes a spec in the refusal). Returns (the ``SavedController`` s, their episode, their simulator)."""
    from freeform.agents.controller_file import read_controller
    from freeform.zoo import resolve

    first = [read_controller(resolve(s)) for s in specs]
    box = tuple(max(b) for b in zip(*([box] if box else []), *(tuple(s.controller.box) for s in first), strict=True))
    saved = [read_controller(s.path, box=box) for s in first]
    control, sim = episode_of(saved[0]), saved[0].sim or SimConfig()
    for spec, s in zip(specs[1:], saved[1:], strict=True):
        if differ := episode_differences(s, control, sim, saved[0].path):
            raise ValueError(f"{who}{spec} plays another episode or simulator than {specs[0]} — {'; '.join(differ)}: "
                             f"{why}")
    return saved, control, sim


class Candidates:
    """The candidates read back and built for one box that holds the bodies, checked to play one episode in one
    simulator (each difference named); ``steering`` where that episode draws a heading (random headings)."""

    def __init__(self, specs: tuple[str, ...], grids: torch.Tensor) -> None:
        from freeform.agents.controller_file import body_box

        if not specs:
            raise ValueError("fit needs at least one candidate controller")
        self.names = [candidate_name(s) for s in specs]
        if len(set(self.names)) < len(self.names):
            raise ValueError(f"--candidates: two of them share a name ({self.names}): give each its own folder")
        self.saved, self.control, self.sim = read_alike(
            specs, "fit tries controllers of one episode and one simulator (the zoo's all are)", body_box(grids),
            who="candidate ")
        self.steering = self.control.headings == "random"


def resolved(how: Fit, c: Candidates) -> Fit:
    """``how`` with what it left to the candidates' task filled in: the recipes (:data:`RECIPES`, or
    :data:`STEERING_RECIPES` for steering), the trial's episodes and the figures' (:data:`TRIAL_EPISODES` and
    ``evaluate``'s ``EPISODES`` for steering, else 1; more than one refused where every episode is the same)."""
    from dataclasses import replace

    who, headings = f"candidate {c.names[0]}", c.control.headings
    return replace(how, presets=how.presets if how.presets is not None else
                   STEERING_RECIPES if c.steering else RECIPES,
                   trial_episodes=figure_episodes(headings, how.trial_episodes, TRIAL_EPISODES, "--trial-episodes", who),
                   episodes=figure_episodes(headings, how.episodes, EPISODES, "--episodes", who))


def trial_draws(how: Fit, c: Candidates) -> tuple[int, int]:
    """The episodes a trial plays, as ``block_env``'s (episodes, first_episode): for steering ``how.trial_episodes``
    after the ``how.episodes`` a figure is measured on (``evaluate``'s), so that no choice is made on a draw that
    reports it; else the one episode (it draws nothing a choice could fit)."""
    how = resolved(how, c)  # (one default: resolved's)
    return (how.trial_episodes, how.episodes) if c.steering else (1, 0)


def recipe(how: Fit, preset: str, bodies: Path, m: int, start: Path | str) -> Any:
    """The run config of ``preset``'s adaptation of the ``m`` bodies in ``bodies``, each starting from a controller
    shaped as ``start`` (its own then loaded): ``how.settings`` over the preset, fit's own keys over both."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from freeform.config import compose

    try:
        return compose(f"experiment={preset}", *how.settings, f"control.bodies={bodies}", f"control.teachers={m}",
                       f"env.num_envs={m * how.copies}", f"control.controller_init={start}",
                       f"trainer.epochs={how.adapt_epochs}", f"seed={how.seed}",
                       # (a recipe's own evaluation: seconds fit's budget would count; no plateau rule to read it)
                       "agent.eval_every=0", "trainer.plateau_on=return")
    except (HydraException, OmegaConfBaseException, ValueError) as e:
        if not how.settings:
            raise
        why = (str(e).splitlines() or [type(e).__name__])[0]
        raise ValueError(f"--set {' '.join(how.settings)}: the adaptation's config ({preset}) refuses it (or fit's "
                         f"own settings with it): {why}") from None


def adaptation(c: Candidates, m: int, how: Fit, bodies: Path) -> list[Any]:
    """Each of ``how.presets``' run configs for ``m`` bodies in ``bodies`` (:func:`recipe`), checked before anything
    is played: ``how.copies`` >= 2 (the leave-one-out baseline needs a sibling), ``how.settings`` that every preset
    takes, each preset's episode the candidates', and at least one candidate of a controller some preset trains
    (:func:`recipe_of`)."""
    if how.copies < 2:
        raise ValueError(f"--copies must be >= 2 (a body's copies are each other's baseline), got {how.copies}")
    how = resolved(how, c)
    if not how.presets:
        raise ValueError("fit adapts by at least one recipe (a preset of conf/experiment/)")
    cfgs = []
    for preset in how.presets:
        cfg = recipe(how, preset, bodies, m, c.saved[0].path)
        differ = described_differences(cfg.control.episode(), c.control, f"experiment={preset}", EPISODE)
        if differ:
            raise ValueError(f"the adaptation ({preset}) plays another episode than the candidates: "
                             f"{'; '.join(differ)}: adapt candidates of its episode, or --adapt-epochs 0")
        cfgs.append(cfg)
    if (recipe_of(c, cfgs) < 0).all():
        s = c.saved[0]
        kwargs = s.controller.init_kwargs
        wanted = "; ".join(f"{p}: {k[0]} controllers ({k[1]} wide, head {k[2]})"
                           for p, k in zip(how.presets, map(trained_kind, cfgs), strict=True))
        raise ValueError(f"no candidate is of a kind the adaptation trains ({wanted}); candidate {c.names[0]} is a "
                         f"{s.kind} controller ({kwargs.get('hidden')} wide, head {kwargs.get('head')}): add one of "
                         "the zoo's students, or --adapt-epochs 0")
    return cfgs


def trained_kind(cfg: Any) -> tuple[str, int, str]:
    """The controller the adaptation ``cfg`` trains: (kind, width, head)."""
    width = cfg.control.hidden if cfg.control.hidden is not None else cfg.agent.hidden
    return cfg.control.controller, width, cfg.control.head


def recipe_of(c: Candidates, cfgs: list[Any]) -> np.ndarray:
    """Which of the recipes ``cfgs`` adapts each candidate ``[C]``: the first that trains its controller (kind,
    width, head: weights of one shape, so each loads into that recipe's bank), -1 where none does — tried, and kept
    where it wins, but not adapted."""
    kinds = [trained_kind(cfg) for cfg in cfgs]
    own = [(s.kind, s.controller.init_kwargs.get("hidden"), s.controller.init_kwargs.get("head")) for s in c.saved]
    return np.array([kinds.index(k) if k in kinds else -1 for k in own])


def trial_decisions(seconds: float | None, control: ControlConfig) -> int:
    """The decisions a trial of ``seconds`` lasts (None: the whole episode's), at least one."""
    if seconds is None:
        return control.steps
    step = control.decision_seconds
    if not (np.isfinite(seconds) and 0 < seconds <= control.steps * step + 1e-9):
        raise ValueError(f"--trial must be in (0, {control.steps * step:g}] seconds (the episode), got {seconds!r}")
    return max(1, min(control.steps, round(seconds / step)))


@torch.no_grad()
def trial_moves(c: Candidates, grids: torch.Tensor, seed: int = 0, draws: tuple[int, int] = (1, 0)) -> np.ndarray:
    """``[D, C, M]``: every candidate's move on every body after each of the episode's D decisions (mean commands),
    the mean over the episodes ``draws`` (:func:`trial_draws`; every candidate along the same headings), all in one
    env of a block of rows a candidate."""
    episodes, first = draws
    env = block_env(grids, c.saved[0], c.control, blocks=len(c.saved), episodes=episodes, seed=seed,
                    first_episode=first)
    groups = [(name, s.controller.eval(), False, False) for name, s in zip(c.names, c.saved, strict=True)]
    after = play(env, groups, c.control.steps, seed).after  # [D, C, M·episodes]: the last is the whole episode's
    return after.reshape(c.control.steps, len(c.saved), len(grids), episodes).mean(-1)


def trials(c: Candidates, grids: torch.Tensor, decisions: int, seed: int = 0, draws: tuple[int, int] = (1, 0),
           ) -> tuple[np.ndarray, np.ndarray]:
    """Every candidate's move on every body after ``decisions`` (what a body's choice is by) and its whole-episode
    move, both ``[C, M]`` (:func:`trial_moves`)."""
    after = trial_moves(c, grids, seed, draws)
    return after[decisions - 1], after[-1]


def chosen(trial: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """Each body's best candidate ``[M]`` by ``trial`` ``[C, M]`` (a tie to the earlier), among the candidates
    ``among`` ``[C]`` (bool; None: all)."""
    return (trial if among is None else np.where(among[:, None], trial, -np.inf)).argmax(0)


def recipe_banks(c: Candidates, grids: torch.Tensor, begin: np.ndarray, which: np.ndarray, how: Fit,
                 scratch: Path) -> list[tuple[str, np.ndarray, Any]]:
    """A bank a recipe (:func:`adapt`'s arguments): (its preset, its bodies' places in ``grids``, its PPO), each
    member loaded with its body's candidate ``begin[i]``."""
    from freeform.run.build import build

    banks = []
    for k in np.unique(which):
        places = np.flatnonzero(which == k)
        bodies = scratch / f"adapting_{how.presets[k]}.npy"
        np.save(bodies, grids[places].numpy())
        _, ppo = build(recipe(how, how.presets[k], bodies, len(places), c.saved[int(begin[places[0]])].path),
                       torch.device("cpu"))
        for j, i in enumerate(places):
            ppo.policy.load_member(j, c.saved[int(begin[i])].controller.state_dict())
        banks.append((how.presets[k], places, ppo))
    return banks


class Adapted(NamedTuple):
    """What :func:`adapt` returns: each body's adapted controller ``[M]``, its move ``[M]`` over the trial's episodes,
    the curve (a row a point; a row a point and body) and the epochs run."""

    members: list[Any]
    moves: np.ndarray
    curve: list[dict]
    per_body: list[dict]
    epochs: int


def adapt(c: Candidates, grids: torch.Tensor, begin: np.ndarray, which: np.ndarray, how: Fit, scratch: Path,
          tried: tuple[np.ndarray, np.ndarray] | None = None, begun: float | None = None) -> Adapted:
    """Each body's candidate ``begin[i]`` trained on it for ``how.adapt_epochs`` epochs (or as many as
    ``how.adapt_seconds`` holds: :class:`Fit`) by the recipe
    ``how.presets[which[i]]`` (the module's docstring; a bank a recipe, its bodies written
    to ``scratch``): each body's adapted controller ``[M]`` (its bank's member), its move on its body ``[M]`` (mean
    command) over the trial's episodes (:func:`trial_draws`: what it is chosen by), and with ``how.curve_every`` the
    adaptation's curve as (a row a point, a row a point and body): ``epoch``, ``seconds`` (a body's share of the wall
    time since ``begun``, measuring left out), ``adapted`` (the move under its bank) and ``kept`` (the trial's pick
    before the first epoch, then the better of the bank and the pick by the trial's episodes: what fit would give
    stopped there) — the bodies' mean in the first, each ``body``'s own in the second. ``tried``: the pick's trial
    figure and its figure, each ``[M]`` (the same for a heading task that draws nothing; for steering the mean of
    its figure episodes). The curve's moves are figures: for steering, the figure episodes', never the trial's."""
    m, how = len(grids), resolved(how, c)  # (idempotent: adapt called alone gets the task's defaults too)
    draws = trial_draws(how, c)
    banks = recipe_banks(c, grids, begin, which, how, scratch)

    def measured(episodes: int, first: int) -> np.ndarray:  # (each bank's bodies along their own draws in the set)
        moves = np.empty(m)
        for _, places, ppo in banks:
            env = block_env(grids[places], c.saved[0], c.control, blocks=1, episodes=episodes, seed=how.seed,
                            first_episode=first, among=(places, m))
            moves[places] = own_moves(ppo.policy, env, how.seed, episodes).reshape(-1, episodes).mean(1)
        return moves

    tried, figure = tried if tried is not None else (None, None)

    curve: list[dict] = []
    per_body: list[dict] = []
    begun = time.perf_counter() if begun is None else begun
    measuring, moved = 0.0, None

    def point(epoch: int) -> None:
        nonlocal measuring, moved
        at = time.perf_counter()
        moved = measured(*draws)
        shown = measured(how.episodes, 0) if c.steering else moved  # (steering: chosen by the trial's, shown by 0 …)
        # (before the first epoch fit keeps the trials' pick at its figure: the bank plays that pick in another
        # batch, whose rounding would lift the max by a hair on one CPU and not on another)
        kept = (np.full(m, np.nan) if tried is None else figure.astype(float) if epoch == 0
                else np.where(moved > tried, shown, figure))
        seconds = (at - begun - measuring) / m
        curve.append({"epoch": epoch, "seconds": seconds, "adapted": float(shown.mean()), "kept": float(kept.mean())})
        per_body.extend({"epoch": epoch, "seconds": seconds, "body": i, "adapted": float(a), "kept": float(k)}
                        for i, (a, k) in enumerate(zip(shown, kept, strict=True)))
        measuring += time.perf_counter() - at

    if how.curve_every:
        point(0)
    done = 0
    with torch.enable_grad():
        while done < how.adapt_epochs:
            at = time.perf_counter()
            for preset, places, ppo in banks:  # (in turn: each bank's epoch is its own bodies' alone)
                stats = ppo.train_epoch()
                of = f"/{how.adapt_epochs}" if how.adapt_seconds is None else f" (of {how.adapt_seconds:g} s a body)"
                print(f"adapting {len(places)} bodies ({preset}): epoch {done + 1}{of}, the epoch's "
                      f"return {stats.get('episode_reward_mean', float('nan')):.3f}", flush=True)
            done += 1
            now = time.perf_counter()  # (another epoch like this one would pass the budget: the last)
            last = done == how.adapt_epochs or (how.adapt_seconds is not None and (
                now - begun - measuring + now - at) / m > how.adapt_seconds)
            if how.curve_every and (done % how.curve_every == 0 or last):
                point(done)
            if last:
                break
    members: list[Any] = [None] * m
    for _, places, ppo in banks:
        for j, i in enumerate(places):
            members[i] = ppo.policy.member(j)
    # (the curve's last point measured the last epoch)
    return Adapted(members, moved if how.curve_every else measured(*draws), curve, per_body, done)


@torch.no_grad()
def alone(nets: list[Any], grids: torch.Tensor, c: Candidates, seed: int = 0, episodes: int = 1) -> np.ndarray:
    """Body i's move ``[M]`` under ``nets[i]``'s mean command, each network given its body's rows alone: what
    ``evaluate`` and ``watch`` of its ``controller.pt`` on its ``body.npy`` report, to the bit (a forward pass rounds
    by the batch it is given; the physics does not, so the bodies share one env, a block of rows each); for
    steering the mean over its ``episodes`` (episodes 0 … K−1: what ``evaluate`` of the file on all of ``grids`` gives
    in row i, but for that rounding)."""
    env = block_env(grids, c.saved[0], c.control, blocks=1, episodes=episodes, seed=seed)
    groups = [(f"body{i}", net.eval(), False, False) for i, net in enumerate(nets)]
    return play(env, groups, c.control.steps, seed).returns.mean(1)  # (group i: body i's episodes)


def fit(grids: torch.Tensor, out: Path, how: Fit) -> list[dict]:
    """A controller for each body of ``grids`` (uint8 ``[M, ρ, ρ, ρ]``): trials, then adaptation where asked; writes
    ``out/body<i>/controller.pt`` (self-contained: ``evaluate`` and ``watch`` read it) beside ``out/body<i>/body.npy``
    and ``out/bodies.csv`` (``body``, ``chosen``, ``mean_command``: the body's move under it, alone, ``controller_file``,
    ``seconds``: the body's share of the wall time, then each candidate's trial figure: for steering the mean of the
    trial's episodes, which ``mean_command``'s are not; a steering body's headings are its row's draws in ``grids``,
    what ``evaluate --episodes K`` of its file on all of ``grids`` gives in row i). Returns the rows."""
    from freeform.agents.controller_file import save_controller
    from freeform.tables import write_rows

    start = time.perf_counter()
    c = Candidates(how.candidates, grids)
    how = resolved(how, c)
    decisions = trial_decisions(how.trial, c.control)
    m = len(grids)
    with tempfile.TemporaryDirectory(prefix="freeform-fit-") as scratch:
        bodies = Path(scratch) / "bodies.npy"
        np.save(bodies, grids.numpy())
        cfgs = adaptation(c, m, how, bodies) if how.adapt_epochs else None  # (refused before anything is played)
        trial, moves = trials(c, grids, decisions, how.seed, trial_draws(how, c))
        choice = chosen(trial)
        nets = [c.saved[int(k)].controller for k in choice]
        labels = [c.names[int(k)] for k in choice]
        if cfgs is not None:  # (each body adapts its best adaptable candidate, and keeps it where it beats the choice)
            kinds = recipe_of(c, cfgs)
            begin = chosen(trial, kinds >= 0)
            tried = moves[choice, np.arange(m)]
            at = time.perf_counter()  # (the pick's figure, for the curve: measuring, left out of the seconds)
            figure = (alone(nets, grids, c, how.seed, how.episodes) if c.steering and how.curve_every
                      else tried)
            begun = start + time.perf_counter() - at
            adapted = adapt(c, grids, begin, kinds[begin], how, Path(scratch), (tried, figure), begun)
            better = adapted.moves > moves[choice, np.arange(m)]
            nets = [adapted.members[i] if better[i] else net for i, net in enumerate(nets)]
            labels = [f"{c.names[int(begin[i])]} + {adapted.epochs} epochs" if better[i] else label
                      for i, label in enumerate(labels)]
    moved = alone(nets, grids, c, how.seed, how.episodes)
    out.mkdir(parents=True, exist_ok=True)
    rows, seconds = [], (time.perf_counter() - start) / m
    for i in range(m):
        path = save_controller(out / f"body{i}" / "controller.pt", nets[i], c.control, c.sim)
        np.save(out / f"body{i}" / "body.npy", grids[i].numpy())
        rows.append({"body": i, "chosen": labels[i], "mean_command": float(moved[i]), "controller_file": str(path),
                     "seconds": seconds, **{f"trial_{n}": float(moves[k, i]) for k, n in enumerate(c.names)}})
    write_rows(out / "bodies.csv", rows)
    if cfgs is not None and how.curve_every:  # (the bodies' mean; body by body beside, for a fraction's band)
        write_rows(out / "adaptation.csv", adapted.curve)
        write_rows(out / "adaptation_bodies.csv", adapted.per_body)
    return rows


def gate(specs: tuple[str, ...], trial: float, out: Path) -> Path:
    """One ``controller.pt`` at ``out`` that tries the controllers ``specs`` (zoo names or paths) in turn within an
    episode, each for ``trial`` seconds, and then plays the one whose trial earned most
    (``freeform.agents.networks.gated.TrialGate``); they must play one episode in one simulator. Returns ``out``."""
    from freeform.agents.controller_file import save_controller
    from freeform.agents.networks.gated import TrialGate

    if out.exists():
        raise FileExistsError(f"--out {out} exists: give a new file (nothing is overwritten)")
    if not specs:
        raise ValueError("gate needs at least one controller")
    saved, control, sim = read_alike(specs, "a gate's controllers share one (the zoo's all do)")
    decisions = trial_decisions(trial, control)
    if decisions * len(saved) >= control.steps:
        raise ValueError(f"{len(saved)} controllers tried for {decisions} decisions each leave none of the episode's "
                         f"{control.steps} to play the best: a shorter --trial, or fewer controllers")
    net = TrialGate.from_controllers([s.controller for s in saved], decisions)
    return save_controller(out, net, control, sim)


def no_earlier_fit(out: Path) -> None:
    """Refuse to write into a folder that holds a fit already (nothing written is lost)."""
    if (out / "bodies.csv").exists():
        raise FileExistsError(f"--out {out} holds a fit already (bodies.csv): give a new folder, or move that one")


__all__ = ["BUDGET_EPOCHS", "DEFAULT_ADAPT_EPOCHS", "EPISODE", "FIT_SETS", "RECIPES", "STEERING_RECIPES",
           "TRIAL_EPISODES", "Adapted", "Candidates", "Fit", "adapt", "adaptation", "alone", "candidate_name", "chosen",
           "episode_differences", "fit", "gate", "no_earlier_fit", "read_alike", "recipe", "recipe_banks", "recipe_of",
           "resolved", "trained_kind", "trial_decisions", "trial_draws", "trials"]
