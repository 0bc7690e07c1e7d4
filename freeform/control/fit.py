"""A controller for each of your bodies: the zoo's controllers tried on it, the best kept, then adapted to it by
PPO — ``freeform-control fit``.

**Trials.** Every candidate (the zoo's :data:`freeform.zoo.TRIED`, the hand-set wave among them) drives every body
by its mean command for one episode, all in one env (a block of rows a candidate); a body's controller is the one
that moved it furthest after the trial's decisions (``--trial SECONDS``; default the whole episode), and its figure
is its whole episode. The mean command is deterministic, so that figure is what ``evaluate`` reports for the body.

**Adaptation** (``--adapt-epochs E`` > 0). Each body's best candidate of the kind the adaptation trains (the zoo's
students; :func:`adaptable` — other candidates, such as per-body controllers of other bodies, are tried and kept
where they win, not adapted) is trained on that body alone for E epochs of PPO — all bodies at once, as one bank of
per-body controllers (``freeform.agents.distill.teachers.TeacherBank``, each body ``--copies`` environments with a
leave-one-out baseline among them), by the ``control_adapt_cpu`` preset's recipe (its learning rate and batch;
``conf/experiment/``; ``--set agent.lr=1e-3`` changes it). Each body then keeps whichever of the adapted and the
chosen controller (its best trial of all) moves it further by its mean command. With ``--curve-every K`` the bodies
are measured every K epochs (and before the first and after the last) into ``adaptation.csv``: what a body gains for
the seconds it costs (the bodies' mean; ``adaptation_bodies.csv`` body by body).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freeform.control.evaluate import block_env, episode_of
from freeform.control.play import own_moves, play
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.envs.control_config import described_differences
from freeform.sim import SimConfig

EPISODE = tuple(f.name for f in fields(ControlConfig))
"""Every field of an episode: what two controllers tried side by side, or a controller and its adaptation, share."""

FIT_SETS = {"control.bodies": "from the bodies", "control.teachers": "one controller a body",
            "control.controller_init": "each body starts from its best candidate of the adaptation's kind",
            "env.num_envs": "give --copies", "trainer.epochs": "give --adapt-epochs", "seed": "give --seed",
            "agent.seed": "give --seed", "experiment": "the preset is fit's"}
"""The adaptation's keys that ``fit`` sets itself (and how a user sets them), which ``--set`` may not name."""

DEFAULT_ADAPT_EPOCHS = 24
"""The adaptation ``fit`` runs unless told otherwise: 24 epochs, about a minute of 2-core time a body (59–72 s on
the held-out bodies; docs/control.md)."""


@dataclass(frozen=True)
class Fit:
    """How ``fit`` works: the candidates (zoo names or ``controller.pt`` paths, tried in this order: a tie goes to
    the earlier), the trial's seconds (None: the whole episode), the adaptation's epochs (0: trials alone), its
    environments per body, the preset whose recipe it follows, and the seed."""

    candidates: tuple[str, ...]
    trial: float | None = None
    adapt_epochs: int = DEFAULT_ADAPT_EPOCHS
    copies: int = 4
    preset: str = "control_adapt_cpu"
    seed: int = 0
    curve_every: int = 0
    """Measure the bodies every this many adaptation epochs (and at 0 and the last) into ``adaptation.csv``; 0:
    never."""
    settings: tuple[str, ...] = ()
    """Hydra overrides of the preset's recipe (``agent.lr=1e-3``), applied before what fit sets itself (the keys of
    :data:`FIT_SETS`, which they may not name)."""

    def __post_init__(self) -> None:
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
        if self.curve_every < 0 or (self.curve_every and not self.adapt_epochs):
            raise ValueError(f"--curve-every {self.curve_every}: a whole number of adaptation epochs >= 0 (0: never), "
                             "with --adapt-epochs > 0 (trials alone have no curve)")


def candidate_name(spec: str) -> str:
    """How tables name a candidate: a zoo name as it is, a file by its folder (``runs/mine/controller.pt``: ``mine``),
    a folder by itself."""
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
    simulator (each difference named), under a heading task that one draw can try (not random headings)."""

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
        if self.control.headings == "random":
            raise ValueError(f"candidate {specs[0]} walks along random headings: the best of several controllers on "
                             "one draw of headings is biased upwards on the next, so fit tries controllers of a "
                             "heading task that one episode tries (headings any or fixed)")


def adaptation(c: Candidates, m: int, how: Fit, bodies: Path) -> Any:
    """The adaptation's run config (``how.preset`` for ``m`` bodies in ``bodies``, ``how.settings`` over it), checked
    before anything is played: ``how.copies`` >= 2 (the leave-one-out baseline needs a sibling), the preset's episode
    the candidates', and at least one candidate of the controller it trains (:func:`adaptable`; the first such one is
    the run's ``control.controller_init``, which each body's own start then replaces)."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from freeform.config import compose

    if how.copies < 2:
        raise ValueError(f"--copies must be >= 2 (a body's copies are each other's baseline), got {how.copies}")

    def composed(start: Path) -> Any:
        try:
            return compose(f"experiment={how.preset}", *how.settings, f"control.bodies={bodies}",
                           f"control.teachers={m}", f"env.num_envs={m * how.copies}",
                           f"control.controller_init={start}", f"trainer.epochs={how.adapt_epochs}",
                           f"seed={how.seed}")
        except (HydraException, OmegaConfBaseException, ValueError) as e:
            if not how.settings:
                raise
            why = (str(e).splitlines() or [type(e).__name__])[0]
            raise ValueError(f"--set {' '.join(how.settings)}: the adaptation's config ({how.preset}) refuses it "
                             f"(or fit's own settings with it): {why}") from None

    cfg = composed(c.saved[0].path)
    differ = described_differences(cfg.control.episode(), c.control, f"experiment={how.preset}", EPISODE)
    if differ:
        raise ValueError(f"the adaptation ({how.preset}) plays another episode than the candidates: "
                         f"{'; '.join(differ)}: adapt candidates of its episode, or --adapt-epochs 0")
    can = adaptable(c, cfg)
    if not can.any():
        s, wanted = c.saved[0], trained_kind(cfg)
        kwargs = s.controller.init_kwargs
        raise ValueError(f"no candidate is of the kind the adaptation ({how.preset}) trains, {wanted[0]} controllers "
                         f"({wanted[1]} wide, head {wanted[2]}); candidate {c.names[0]} is a {s.kind} controller "
                         f"({kwargs.get('hidden')} wide, head {kwargs.get('head')}): add one of the zoo's students, "
                         "or --adapt-epochs 0")
    return cfg if can[0] else composed(c.saved[int(np.argmax(can))].path)


def trained_kind(cfg: Any) -> tuple[str, int, str]:
    """The controller the adaptation ``cfg`` trains: (kind, width, head)."""
    width = cfg.control.hidden if cfg.control.hidden is not None else cfg.agent.hidden
    return cfg.control.controller, width, cfg.control.head


def adaptable(c: Candidates, cfg: Any) -> np.ndarray:
    """Which candidates ``[C]`` the adaptation ``cfg`` can start from: those of the controller it trains (kind,
    width, head: weights of one shape, so each loads into the bank). The others are tried, and kept where they win,
    but not adapted."""
    return np.array([(s.kind, s.controller.init_kwargs.get("hidden"), s.controller.init_kwargs.get("head"))
                     == trained_kind(cfg) for s in c.saved])


def trial_decisions(seconds: float | None, control: ControlConfig) -> int:
    """The decisions a trial of ``seconds`` lasts (None: the whole episode's), at least one."""
    if seconds is None:
        return control.steps
    step = control.decision_seconds
    if not (np.isfinite(seconds) and 0 < seconds <= control.steps * step + 1e-9):
        raise ValueError(f"--trial must be in (0, {control.steps * step:g}] seconds (the episode), got {seconds!r}")
    return max(1, min(control.steps, round(seconds / step)))


@torch.no_grad()
def trials(c: Candidates, grids: torch.Tensor, decisions: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Every candidate's move on every body after ``decisions`` (what a body's choice is by) and its whole-episode
    move (its figure), both ``[C, M]`` (mean commands)."""
    env = block_env(grids, c.saved[0], c.control, blocks=len(c.saved), seed=seed)
    groups = [(name, s.controller.eval(), False, False) for name, s in zip(c.names, c.saved, strict=True)]
    played = play(env, groups, c.control.steps, seed)
    return played.after[decisions - 1], played.returns


def chosen(trial: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """Each body's best candidate ``[M]`` by ``trial`` ``[C, M]`` (a tie to the earlier), among the candidates
    ``among`` ``[C]`` (bool; None: all)."""
    return (trial if among is None else np.where(among[:, None], trial, -np.inf)).argmax(0)


def adapt(c: Candidates, grids: torch.Tensor, begin: np.ndarray, how: Fit, cfg: Any,
          tried: np.ndarray | None = None, begun: float | None = None,
          ) -> tuple[Any, np.ndarray, tuple[list[dict], list[dict]]]:
    """Each body's candidate ``begin[i]`` (an adaptable one) trained on it for ``how.adapt_epochs`` epochs (the
    module's docstring; ``cfg`` from :func:`adaptation`): the bank of adapted controllers, each one's whole-episode
    move on its body ``[M]`` (mean command), and with ``how.curve_every`` the adaptation's curve as (a row a point,
    a row a point and body): ``epoch``, ``seconds`` (a body's share of the wall time since ``begun``, measuring left out), ``adapted`` (the
    move under the bank) and ``kept`` (under the better of the bank and the trial, ``tried`` ``[M]``: what fit would
    give stopped there) — the bodies' mean in the first, each ``body``'s own in the second."""
    from freeform.run.build import build

    m = len(grids)
    _, ppo = build(cfg, torch.device("cpu"))
    bank = ppo.policy
    for i in range(m):
        bank.load_member(i, c.saved[int(begin[i])].controller.state_dict())

    def measured() -> np.ndarray:
        return own_moves(bank, block_env(grids, c.saved[0], c.control, blocks=1, seed=how.seed), how.seed)

    curve: list[dict] = []
    per_body: list[dict] = []
    begun = time.perf_counter() if begun is None else begun
    measuring, moved = 0.0, None

    def point(epoch: int) -> None:
        nonlocal measuring, moved
        at = time.perf_counter()
        moved = measured()
        kept = np.maximum(moved, tried) if tried is not None else np.full(m, np.nan)
        seconds = (at - begun - measuring) / m
        curve.append({"epoch": epoch, "seconds": seconds, "adapted": float(moved.mean()), "kept": float(kept.mean())})
        per_body.extend({"epoch": epoch, "seconds": seconds, "body": i, "adapted": float(a), "kept": float(k)}
                        for i, (a, k) in enumerate(zip(moved, kept, strict=True)))
        measuring += time.perf_counter() - at

    if how.curve_every:
        point(0)
    with torch.enable_grad():
        for epoch in range(how.adapt_epochs):
            stats = ppo.train_epoch()
            print(f"adapting {m} bodies: epoch {epoch + 1}/{how.adapt_epochs}, the epoch's return "
                  f"{stats.get('episode_reward_mean', float('nan')):.3f}", flush=True)
            if how.curve_every and ((epoch + 1) % how.curve_every == 0 or epoch + 1 == how.adapt_epochs):
                point(epoch + 1)
    # (the curve's last point measured the last epoch)
    return bank, moved if how.curve_every else measured(), (curve, per_body)


@torch.no_grad()
def alone(nets: list[Any], grids: torch.Tensor, c: Candidates, seed: int = 0) -> np.ndarray:
    """Body i's move ``[M]`` under ``nets[i]``'s mean command, each network given its body's row alone: what
    ``evaluate`` and ``watch`` of its ``controller.pt`` on its ``body.npy`` report, to the bit (a forward pass rounds
    by the batch it is given; the physics does not, so the bodies share one env, a block of one row each)."""
    env = block_env(grids, c.saved[0], c.control, blocks=1, seed=seed)
    groups = [(f"body{i}", net.eval(), False, False) for i, net in enumerate(nets)]
    return play(env, groups, c.control.steps, seed).returns[:, 0]


def fit(grids: torch.Tensor, out: Path, how: Fit) -> list[dict]:
    """A controller for each body of ``grids`` (uint8 ``[M, ρ, ρ, ρ]``): trials, then adaptation where asked; writes
    ``out/body<i>/controller.pt`` (self-contained: ``evaluate`` and ``watch`` read it) beside ``out/body<i>/body.npy``
    and ``out/bodies.csv`` (``body``, ``chosen``, ``mean_command``: the body's move under it, alone, ``controller_file``,
    ``seconds``: the body's share of the wall time, then each candidate's trial figure). Returns the rows."""
    from freeform.agents.controller_file import save_controller
    from freeform.tables import write_rows

    start = time.perf_counter()
    c = Candidates(how.candidates, grids)
    decisions = trial_decisions(how.trial, c.control)
    m = len(grids)
    with tempfile.TemporaryDirectory(prefix="freeform-fit-") as scratch:
        bodies = Path(scratch) / "bodies.npy"
        np.save(bodies, grids.numpy())
        cfg = adaptation(c, m, how, bodies) if how.adapt_epochs else None  # (refused before anything is played)
        trial, moves = trials(c, grids, decisions, how.seed)
        choice = chosen(trial)
        nets = [c.saved[int(k)].controller for k in choice]
        labels = [c.names[int(k)] for k in choice]
        if cfg is not None:  # (each body adapts its best adaptable candidate, and keeps it where it beats the choice)
            begin = chosen(trial, adaptable(c, cfg))
            bank, adapted, (curve, per_body) = adapt(c, grids, begin, how, cfg, moves[choice, np.arange(m)], start)
            better = adapted > moves[choice, np.arange(m)]
            nets = [bank.member(i) if better[i] else net for i, net in enumerate(nets)]
            labels = [f"{c.names[int(begin[i])]} + {how.adapt_epochs} epochs" if better[i] else label
                      for i, label in enumerate(labels)]
    moved = alone(nets, grids, c, how.seed)
    out.mkdir(parents=True, exist_ok=True)
    rows, seconds = [], (time.perf_counter() - start) / m
    for i in range(m):
        path = save_controller(out / f"body{i}" / "controller.pt", nets[i], c.control, c.sim)
        np.save(out / f"body{i}" / "body.npy", grids[i].numpy())
        rows.append({"body": i, "chosen": labels[i], "mean_command": float(moved[i]), "controller_file": str(path),
                     "seconds": seconds, **{f"trial_{n}": float(moves[k, i]) for k, n in enumerate(c.names)}})
    write_rows(out / "bodies.csv", rows)
    if cfg is not None and how.curve_every:  # (the bodies' mean; body by body beside, for a fraction's band)
        write_rows(out / "adaptation.csv", curve)
        write_rows(out / "adaptation_bodies.csv", per_body)
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


__all__ = ["DEFAULT_ADAPT_EPOCHS", "EPISODE", "FIT_SETS", "Candidates", "Fit", "adapt", "adaptable", "adaptation",
           "alone", "candidate_name", "chosen", "episode_differences", "fit", "gate", "no_earlier_fit", "read_alike",
           "trained_kind", "trial_decisions", "trials"]

