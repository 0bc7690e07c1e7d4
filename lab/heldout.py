"""Controllers on bodies they never saw (zero-shot): ``python -m lab.control --evaluate PATH --bodies
BODIES.npy`` (:func:`evaluate_bodies`; the held-out sets are ``lab.heldout_bodies``').

Each body is played by the controller (stochastic and by its mean command), the controller with its sensed
channels zeroed, an untrained one, the hand-set travelling wave and, with ``--per-body N``, the first N bodies' own
controllers (per-body control: a teacher bank trained once by ``freeform-train`` and cached, or a teacher run
named with ``--per-body-run``), all against each body's open-loop gait in the same window and headings.
Writes ``bodies.csv`` (a row per body), ``summary.csv`` (means with 99 % bands across bodies, paired differences,
the fraction of per-body control reached and of bodies beyond their own gait) and ``run.json``.

Several sets evaluated apart (the 93 held-out bodies: ``design_unseen``, ``grown``, ``hand_built``) pooled into one
table over all their bodies (:func:`pool`)::

    python -m lab.heldout --pool DIR1 DIR2 DIR3 --out DIR
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments.common import mean_band, missing_figure, summary_row, write_rows
from freeform.agents.controller_file import controller_for, read_controller
from freeform.agents.networks import rebuild
from freeform.agents.networks.controller_heads import HandSetWave, wave_at_gain
from freeform.agents.networks.controllers import CONTROLLERS, with_wave_gain
from freeform.agents.networks.group_average import GroupAveraged, check_turnable
from freeform.control.bodies import read_bodies
from freeform.control.play import SENSED, BankOnBodies, Played, hand_set_wave, play  # noqa: F401 (the lab imports them from here)
from freeform.envs.control import (
    ControlConfig,
    ControlEnv,
    open_loop_displacement,
    open_loop_moves,
)
from freeform.envs.control_config import described_differences
from freeform.run.resume import EXECUTION_KEYS, override_key
from freeform.sim import SimConfig
from freeform.zoo import resolve
from lab.paired import check_drift, read_table, same_gait, warn_hosts


@dataclass
class PerBody:
    """``--per-body N``: per-body controllers for the first ``n`` bodies, trained by ``freeform-train
    experiment=<preset>`` (a bank: ``control.teachers=n``, ``copies`` environments per body, the evaluation's
    episode settings: the controller's, ``--headings`` included) or read from ``cache`` (a run directory named by
    the bodies and settings, resumed where a run stopped early)."""

    n: int
    preset: str = "control_teachers_cpu"
    copies: int = 4
    overrides: tuple[str, ...] = ()
    cache: Path = Path("runs/per_body")
    run: Path | None = None
    """A teacher run to read instead (``control.teachers`` = n, its bodies the first n given: checked)."""


def _hydra_value(value: Any) -> str:
    return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


_KEYLESS_DEFAULTS = {("frame", "world")}


def episode_overrides(control: ControlConfig) -> list[str]:
    """``control``'s episode as Hydra overrides (``control.<field>=<value>``), for a run that must play it."""
    # (a field added since the caches were made stays out of the overrides and the key at its default: old caches hold)
    return [f"control.{k}={_hydra_value(v)}" for k, v in vars(control).items()
            if k != "privileged_critic" and (k, v) not in _KEYLESS_DEFAULTS]


def per_body_cache_run(bodies: np.ndarray, per: PerBody, control: ControlConfig) -> tuple[Path, list[str]]:
    """The cache's run directory for per-body controllers of ``bodies`` (uint8 ``[n, ρ, ρ, ρ]``) under the episode
    settings ``control``, named by a hash of the bodies and the overrides, and those overrides of ``per.preset``."""
    overrides = [f"control.teachers={per.n}", f"env.num_envs={per.n * per.copies}", *episode_overrides(control),
                 *per.overrides]
    # (execution keys such as trainer.threads stay out of the name: the same cache continues with more threads, or on
    # another device, as any run may resume)
    named = [o for o in overrides if override_key(o) not in EXECUTION_KEYS]
    key = hashlib.sha1(bodies.tobytes() + "|".join([per.preset, *named]).encode()).hexdigest()[:12]
    return per.cache / f"{per.preset}_{per.n}_{key}", overrides


def per_body_bank(grids: torch.Tensor, per: PerBody, control: ControlConfig, sim: SimConfig) -> Any:
    """The bank of per-body controllers for ``grids[:per.n]`` (:class:`PerBody`), trained or read from the cache;
    its run's physics must be ``sim`` (the evaluated controller's)."""
    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint
    from freeform.config import compose, from_container
    from freeform.run.trainer import flattened
    from freeform.train import train

    if not 1 <= per.n <= len(grids):
        raise ValueError(f"--per-body {per.n}: must be in 1 … {len(grids)} (the bodies given)")
    bodies = grids[: per.n].numpy()
    if per.run is not None:
        return _teacher_run(per.run, bodies, control, sim)
    run, overrides = per_body_cache_run(bodies, per, control)
    run.mkdir(parents=True, exist_ok=True)
    np.save(run / "bodies.npy", bodies)
    cfg = compose(f"experiment={per.preset}", f"control.bodies={run / 'bodies.npy'}", *overrides,
                  "trainer.render_every=0", "trainer.progress=false")
    last = run / "checkpoints" / "last.pt"
    saved = load_checkpoint(last) if last.is_file() else None
    flat = saved is not None and flattened(cfg, saved.get("return_curve", []),
                                           saved.get("eval_curve", []))  # (trained until its curve flattened)
    if saved is None or (int(saved["epoch"]) < cfg.trainer.epochs and not flat):
        print(f"per-body controllers: training {per.n} in {run} ({cfg.trainer.epochs} epochs)", flush=True)
        with torch.enable_grad():  # (called from the evaluation, which computes no gradients)
            result = train(cfg, run)  # (trainer.resume=auto continues a run that stopped early)
        if result.stopped:  # (a stop signal: the same command continues the cache's run; nothing is evaluated)
            raise SystemExit(f"per-body controllers: training stopped ({result.stopped}) after epoch {result.epochs} "
                             f"in {run}; the same command continues it")
    payload = load_checkpoint(last)
    if other := ControlEnv.physics_differences(from_container(payload["config"]).sim, sim, control, "the cache"):
        raise ValueError(f"--per-body: the per-body controllers in {run} were trained in another simulator than the "
                         f"evaluated controller's: {other} (give the evaluated controller's sim.* values with "
                         "--per-body-set)")
    return bank_from_checkpoint(payload, str(run))


def _teacher_run(run: Path, bodies: np.ndarray, control: ControlConfig, sim: SimConfig) -> Any:
    """The bank of the teacher run ``run``, whose bodies (``freeform.run.build.teacher_bodies``) must be
    ``bodies``, whose interface and task the evaluation's (``control``: ``described_differences``; teachers
    without the response channels drive an evaluation that has them: a bank reads its own channels, the first)
    and whose physics ``sim``'s (``ControlEnv.physics_differences``)."""
    from freeform.body import largest_component
    from freeform.run.build import read_teacher_run

    teachers = read_teacher_run(run, f"--per-body-run {run}")
    differ = described_differences(teachers.config.control, control, "the teacher run", bank=True)
    if differ:
        raise ValueError(f"--per-body-run {run}: its teachers were trained for another controller interface or task "
                         f"than this evaluation's — {'; '.join(differ)}: give a teacher run of the evaluated "
                         "controller's settings (and --headings)")
    if other := ControlEnv.physics_differences(teachers.config.sim, sim, control, "the teacher run"):
        raise ValueError(f"--per-body-run {run}: its teachers were trained in another simulator than the evaluated "
                         f"controller's: {other} (give a teacher run of the evaluated controller's sim.* values)")
    theirs = largest_component(teachers.bodies).numpy()
    if teachers.bank.teachers != len(bodies) or not np.array_equal(theirs, bodies):
        raise ValueError(f"--per-body-run {run}: its {teachers.bank.teachers} teachers' bodies are not the first "
                         f"{len(bodies)} bodies given (save them from its records: final_grids[:M])")
    return teachers.bank


@dataclass(frozen=True)
class Evaluation:
    """How :func:`evaluate_bodies` plays the bodies: ``episodes`` per body, the heading task (None: the
    controller's own), the seed of its untrained controller, its episodes and noise, the group the trained
    controller is averaged over (None: none) and the wave gain it plays at (None: its file's)."""

    episodes: int
    headings: str | None = None
    seed: int = 0
    symmetrize: str | None = None
    wave_gain: float | None = None


@torch.no_grad()
def evaluate_bodies(source: Path, bodies: Path, out: Path, how: Evaluation, per_body: PerBody | None = None,
                    wave: HandSetWave | None = None) -> tuple[list[dict], list[dict]]:
    """Zero-shot evaluation of a saved controller (``source``: a ``controller.pt``, a folder holding one, or a
    control run's directory) on the bodies of ``bodies`` (:func:`read_bodies`), ``how.episodes`` stochastic
    episodes each (:class:`Evaluation`), under the controller's own ``ControlConfig`` (``how.headings`` overrides its
    heading task). One env runs every
    body × episode once per group, the groups with the same headings (the same draws): the controller, the
    controller's mean command (deterministic: what it learned, without its exploration noise), the controller with
    its sensed channels zeroed (:data:`SENSED`: a controller that only replays the clock loses nothing), an untrained
    controller of the same architecture (seeded ``how.seed``), stochastic and its mean command (what the architecture
    does before learning: the open-loop gait for most heads, the hand-set travelling wave for a ``wave`` head), the
    hand-set wave's mean command whatever the controller's head (:func:`hand_set_wave`; with strokes), and with
    ``per_body`` each of the first N bodies' own controller (:class:`PerBody`, stochastic). The box is the one the
    controller trained in where the bodies fit it, else theirs (refused for the MLP, which fits one box). With
    ``how.symmetrize`` (a group of ``freeform.envs.symmetry.GROUPS``) the trained controller's three groups are its
    average over that group's turns and mirrors (:class:`~freeform.agents.networks.group_average.GroupAveraged`); the
    untrained and reference controllers are not averaged. With ``how.wave_gain`` the trained controller's wave head
    plays at that gain (:func:`~freeform.agents.networks.controllers.with_wave_gain`: the hand-set wave plus the gain × what
    it learnt).

    Writes ``out/bodies.csv`` (per body: its voxels and actuated voxels as simulated, its open-loop sine gait over
    the same window and headings, the controller's mean over its episodes and that mean's 99 % band, its mean
    command's, the untrained controller's, the hand-set wave's and the per-body controller's means) and
    ``out/summary.csv`` (the means over the bodies with 99 % bands across bodies, then paired differences per body
    — mean command minus open loop, stochastic minus untrained, mean command minus the untrained mean command —
    whose bands leave out the across-body spread, and the fractions of bodies moved beyond their own gait; with
    ``per_body`` the controller and its own per-body controllers
    on the first N bodies, and the fraction of per-body control the controller reaches), and ``out/run.json``.
    Returns (the body rows, the summary rows)."""
    saved = read_controller(resolve(source))  # (a zoo name, or a path)
    sim = saved.sim or SimConfig()
    grids = read_bodies(bodies, len(sim.materials))
    trained = tuple(saved.controller.box)
    saved = controller_for(saved.path, grids)  # (its own box where the bodies fit it; the MLP refused otherwise)
    control = evaluated_control(saved, how)
    m, n, box = len(grids), how.episodes, tuple(saved.controller.box)
    controller = (saved.controller if how.wave_gain is None else with_wave_gain(saved.controller, how.wave_gain))
    controller = controller.eval()
    groups = _groups(controller, saved.kind, how.seed)  # (seeded before the bank, which may train)
    bank = per_body_bank(grids, per_body, control, sim) if per_body is not None else None
    blocks = len(groups) + (control.stroke_periods >= 1) + 2 * (bank is not None)  # (one block of rows a group)
    env = ControlEnv(grids.repeat_interleave(n, 0).repeat(blocks, 1, 1, 1), sim=sim, control=control, seed=how.seed,
                     box=box, first_env=np.tile(np.arange(m * n), blocks))
    if how.symmetrize:
        averaged = GroupAveraged(controller, env.symmetry(how.symmetrize))
        groups = [(name, averaged if net is controller else net, *rest) for name, net, *rest in groups]
    if control.stroke_periods >= 1:
        groups.append(("hand_set_wave", hand_set_wave(env, controller, wave), False, False))
    if bank is not None:
        rows_body = torch.arange(m).repeat_interleave(n)
        own = BankOnBodies(bank, torch.where(rows_body < per_body.n, rows_body, 0), box)
        groups += [("per_body", own, False, True), ("per_body_mean_command", own, False, False)]
    returns, _, obs, heading = play(env, groups, control.steps, how.seed)
    moves = open_loop_moves(grids, sim, control)  # [M, 2]
    along = open_loop_displacement(grids.repeat_interleave(n, 0), sim, control, headings=heading[: m * n],
                                   planar=control.headings == "any", moves=np.repeat(moves, n, 0)).reshape(m, n)
    per_group = {name: returns[g].reshape(m, n) for g, (name, *_) in enumerate(groups)}
    if bank is not None:
        per_group["per_body"][per_body.n:] = per_group["per_body_mean_command"][per_body.n:] = np.nan
    rows = _body_rows(per_group, along.mean(1), obs[: m * n : n], env)
    summary = _summary(per_group, along.mean(1), saved.kind, how.seed, per_body.n if bank is not None else 0,
                       how.symmetrize, played_gain(controller))
    _write(out, rows, summary, {"controller": str(saved.path), "kind": saved.kind, "symmetrize": how.symmetrize,
                                "wave_gain": played_gain(controller),
                                "bodies": str(bodies), "body_count": m, "episodes_per_body": n, "box": list(box),
                                "trained_box": list(trained), "seed": how.seed, "control": vars(control),
                                "per_body": None if per_body is None else {**vars(per_body), "cache": str(per_body.cache)}})
    return rows, summary


def evaluated_control(saved: Any, how: Evaluation) -> ControlConfig:
    """The episode the bodies are played in (``freeform.control.evaluate.episode_of``: the controller's own, along
    ``how.headings`` where given, warned); a ``how.symmetrize`` group that changes the task is refused here, before
    any per-body bank is trained."""
    from freeform.control.evaluate import episode_of

    control = episode_of(saved, how.headings)
    if how.symmetrize:
        check_turnable("--symmetrize", how.symmetrize, control.headings, control.frame, {"the controller": saved.kind})
    return control


def _groups(controller: torch.nn.Module, kind: str, seed: int) -> list[tuple]:
    """The groups every evaluation plays, ``(name, net, sensed channels zeroed, stochastic)``: the controller, its
    mean command, it with its sensed channels zeroed, and an untrained controller of its kind (seeded ``seed``, at
    gain 1: the hand-set wave plus its initial weights' small change), stochastic and by its mean command."""
    torch.manual_seed(seed)
    kwargs = controller.init_kwargs
    untrained = rebuild(CONTROLLERS[kind], {**kwargs, "wave": wave_at_gain(kwargs["wave"], 1.0)}
                        if "wave" in kwargs else kwargs).eval()
    return [("controller", controller, False, True), ("mean_command", controller, False, False),
            ("zeroed", controller, True, True), ("untrained", untrained, False, True),
            ("untrained_mean_command", untrained, False, False)]


def played_gain(controller: torch.nn.Module) -> float | None:
    """The wave gain ``controller`` plays at (``HandSetWave.gain``), None at 1 or without a wave head: what a table
    records, so that tables of one controller pool whether its gain came from its file or from ``--wave-gain``."""
    gain = (getattr(controller, "wave", None) or {}).get("gain", 1.0)
    return None if gain == 1.0 else float(gain)


def _body_rows(per_group: dict[str, np.ndarray], open_loop: np.ndarray, last_obs: torch.Tensor,
               env: ControlEnv) -> list[dict]:
    """``bodies.csv``'s rows: a body's voxels and muscles as simulated (from an observation of its first episode's
    row), its open-loop gait and every group's mean over its episodes (the controller's with its 99 % band)."""
    filled = last_obs[:, env.filled_channel].flatten(1).sum(1)  # (the next episode's: the same bodies)
    # (voxels, not action channels: a stroke's mask holds each muscle twice, once per (a, b))
    actuated = last_obs[:, env.channels.index("actuated")].flatten(1).sum(1)
    rows = []
    for i in range(len(open_loop)):
        mean, band = mean_band(per_group["controller"][i])
        row = {"body": i, "voxels": int(filled[i]), "actuated": int(actuated[i]), "open_loop": float(open_loop[i]),
               "controller": float(mean), "band99": float(band)}
        row.update({name: float(v[i].mean()) for name, v in per_group.items() if name not in ("controller", "zeroed")})
        rows.append(row)
    return rows


def _summary(per_group: dict[str, np.ndarray], open_loop: np.ndarray, kind: str, seed: int, n_own: int,
             symmetrize: str | None = None, wave_gain: float | None = None) -> list[dict]:
    """``summary.csv``: the means over the bodies (99 % bands across bodies), then the paired differences per body
    (each body against itself: same headings, same noise streams, so the across-body spread cancels), the
    fractions of bodies beyond their own gait, and with per-body controllers on the first ``n_own`` bodies the
    controller and theirs there (and theirs beyond the gait) and the fraction reached."""
    body = {name: v.mean(1) for name, v in per_group.items()}
    trained = f"{kind}, averaged over the {symmetrize} group" if symmetrize else kind
    trained += f", wave gain {wave_gain:g}" if wave_gain is not None else ""
    summary = [summary_row("open loop (each body's sine gait, same window and headings)", open_loop),
               summary_row(f"controller ({trained}, stochastic)", body["controller"]),
               summary_row(f"controller ({trained}, mean command)", body["mean_command"]),
               summary_row("controller, sensed channels zeroed (rel, vel, strain, contact)", body["zeroed"]),
               summary_row(f"untrained controller ({kind}, seed {seed}, stochastic)", body["untrained"]),
               summary_row(f"untrained controller ({kind}, seed {seed}, mean command)", body["untrained_mean_command"]),
               summary_row("paired per body: controller (mean command) minus open loop",
                           body["mean_command"] - open_loop, paired=True),
               summary_row("paired per body: controller (stochastic) minus untrained (stochastic)",
                           body["controller"] - body["untrained"], paired=True),
               summary_row("paired per body: controller (mean command) minus untrained (mean command)",
                           body["mean_command"] - body["untrained_mean_command"], paired=True),
               *(_beyond_gait(f"controller ({how})", body[key], open_loop)
                 for how, key in (("stochastic", "controller"), ("mean command", "mean_command")))]
    if "hand_set_wave" in body:
        summary.append(summary_row("hand-set travelling wave (mean command)", body["hand_set_wave"]))
    pairs = (("stochastic", "per_body", "controller"), ("mean command", "per_body_mean_command", "mean_command"))
    for how, theirs, mine in pairs if n_own else ():
        own, yours = body[theirs][:n_own], body[mine][:n_own]
        summary += [summary_row(f"per-body controllers ({how}; the first {n_own} bodies)", own),
                    _beyond_gait(f"per-body controllers ({how})", own, open_loop[:n_own]),
                    summary_row(f"controller ({how}) on those {n_own} bodies", yours),
                    _ratio_row(f"fraction of per-body control ({how}): controller mean / per-body mean "
                               f"({n_own} bodies)", yours.mean() / own.mean(), n_own)]
    return summary


def _ratio_row(what: str, ratio: float, bodies: int) -> dict:
    """A summary row of one ratio of means over ``bodies`` bodies (no band: one number)."""
    return {**summary_row(what, np.array([ratio])), "band99": float("nan"), "n": bodies}


def _beyond_gait(who: str, moved: np.ndarray, open_loop: np.ndarray) -> dict:
    """The fraction of bodies that ``who`` moves further than their own open-loop gait (the band: the fraction's)."""
    return summary_row(f"fraction of bodies beyond their own gait: {who}", (moved > open_loop).astype(float))


def _write(out: Path, rows: list[dict], summary: list[dict], run: dict) -> None:
    write_rows(out / "bodies.csv", rows)
    write_rows(out / "summary.csv", summary)
    (out / "run.json").write_text(json.dumps(run, indent=1, default=str))
    for row in summary:
        print(f"{row['what']}: {row['mean']:.3f} ± {row['band99']:.3f} (n = {row['n']} bodies)")


POOLED = ("open_loop", "controller", "mean_command", "hand_set_wave")
"""The ``bodies.csv`` columns a pooled table reads (each set must have them: a controller with strokes)."""
PER_BODY = ("per_body", "per_body_mean_command")
"""The per-body columns, pooled where every body of every set has them (``--per-body N``, N its body count, or
``--per-body-from``) and left out where no body has them (a table with no per-body reference)."""


def _reference_sets(reference: Path, count: int) -> list[list[dict]]:
    """``--per-body-from``: an earlier pooled table's rows (its folder, or its bodies CSV file as the results keep
    it: ``heldout93/<name>_bodies.csv``), one list per set in its order (``count`` of them)."""
    groups: dict[str, list[dict]] = {}
    for row in read_table(reference, f"--per-body-from {reference}", "--pool, or its bodies CSV"):
        groups.setdefault(row.get("set", ""), []).append(row)
    if "" in groups or len(groups) != count:
        raise ValueError(f"--per-body-from {reference}: a pooled table of {count} sets is needed (an output folder "
                         f"of --pool), and it holds {len(groups)}")
    if any(c not in row for rows in groups.values() for row in rows for c in PER_BODY):
        raise ValueError(f"--per-body-from {reference}: a pooled table without per-body columns (its sets were "
                         "evaluated without --per-body): nothing to take")
    return list(groups.values())


def _take_per_body(table: list[dict], reference: list[dict], folder: Path, source: Path) -> str | None:
    """Each body's per-body columns from ``reference`` (the same set in an earlier pooled table), in place; the same
    body under the same episode settings walks its own gait the same — to the bit on one host, within
    :data:`lab.paired.HOST_DRIFT` on another —, so the open-loop figures must agree. Returns the drift of
    another host in words (:func:`~lab.paired.check_drift`), None on one host."""
    if len(reference) != len(table):
        raise ValueError(f"--per-body-from {source}: its set for {folder} holds {len(reference)} bodies, and "
                         f"{folder} {len(table)}")
    for mine, theirs in zip(table, reference, strict=True):
        gait = (float(mine["open_loop"]), float(theirs["open_loop"]))
        if mine["body"] != theirs["body"] or not same_gait(*gait):
            raise ValueError(f"--per-body-from {source}: body {mine['body']} of {folder} walked its own gait "
                             f"{gait[0]:.6f} here and {gait[1]:.6f} there: not the same bodies, or other episode "
                             "settings (evaluate with the reference's --headings, --eval-episodes and seed)")
        mine["per_body"], mine["per_body_mean_command"] = theirs["per_body"], theirs["per_body_mean_command"]
    return check_drift([float(r["open_loop"]) for r in table], [float(r["open_loop"]) for r in reference],
                       f"--per-body-from {source}: {folder}")


def pool(sets: list[Path], out: Path, per_body_from: Path | None = None) -> list[dict]:
    """Evaluations of one controller on several sets of bodies (``evaluate_bodies``' output folders) as one: their
    ``bodies.csv`` rows together (a ``set`` column: the folder's name) and a ``summary.csv`` over all the bodies —
    the means, the mean command against the hand-set wave (paired per body, and as a ratio), the fractions beyond
    their own gait, and where every body has per-body columns (:data:`PER_BODY`; none may have them: left out)
    the fractions of per-body control. Refused, naming the folder, where a set lacks a column or a value, has
    per-body values on some bodies only, or was evaluated with
    another controller kind, episode settings, episode count or seed; ``run.json`` lists each set's controller
    file (the same weights may sit in a run and in its ``controller.pt``) and each set's bodies (``sets``: the
    ``.npy`` each set was evaluated on and its body count, which ``lab.student_scaling`` compares).
    ``per_body_from``: an earlier pooled table of the same sets, in the same order, whose per-body columns are
    taken instead of the sets' own (sets evaluated without ``--per-body``: no per-body controllers trained
    again); each body's open-loop figure must equal the reference's."""
    reference = _reference_sets(per_body_from, len(sets)) if per_body_from is not None else None
    tables, controllers, settings, sources, drifts = [], [], [], [], []
    for i, folder in enumerate(sets):
        table = read_table(Path(folder) / "bodies.csv", f"--pool {folder}", "--evaluate PATH --bodies ...")
        if reference is not None:
            drifts.append(_take_per_body(table, reference[i], folder, per_body_from))
        missing = [c for c in POOLED if not table or c not in table[0]]
        if missing:
            raise ValueError(f"--pool {folder}: bodies.csv lacks {missing} (the hand-set wave's column needs a "
                             "controller with strokes)")
        gap = next(((r["body"], c) for r in table for c in POOLED if missing_figure(r[c])), None)
        if gap is not None:
            raise ValueError(f"--pool {folder}: bodies.csv has no {gap[1]} for body {gap[0]}")
        if sum(c in table[0] for c in PER_BODY) == 1:
            raise ValueError(f"--pool {folder}: bodies.csv has one of {list(PER_BODY)} and not the other (a table "
                             "from before the mean command's per-body column: evaluate it again)")
        if not (Path(folder) / "run.json").is_file():
            raise ValueError(f"--pool {folder}: no run.json beside bodies.csv (a run record, not kept in git: "
                             "evaluate the set again with python -m lab.control --evaluate ... --out FOLDER, which "
                             "writes both)")
        run = json.loads((Path(folder) / "run.json").read_text())
        setting = {k: run.get(k) for k in ("kind", "symmetrize", "wave_gain", "control", "episodes_per_body", "seed")}
        if settings and setting != settings[0]:
            differ = [k for k in setting if setting[k] != settings[0][k]]
            raise ValueError(f"--pool {folder}: evaluated with other settings than {sets[0]} ({differ} differ): "
                             "evaluate every set with the same controller, --headings, --symmetrize, "
                             "--wave-gain, --eval-episodes and seed")
        settings.append(setting)
        controllers.append(run.get("controller"))
        sources.append({"bodies": run.get("bodies"), "n": len(table)})
        tables.append(table)
    warn_hosts([d for d in drifts if d])
    columns = (*POOLED, *_per_body_columns(tables, sets))
    rows = [{"set": str(folder), **{c: r[c] for c in ("body", *columns)}}
            for folder, table in zip(sets, tables, strict=True) for r in table]
    summary = _pooled_summary({c: np.array([float(r[c]) for r in rows]) for c in columns})
    _write(out, rows, summary, {"pooled": [str(p) for p in sets], "controllers": controllers,
                                "control": settings[0]["control"],  # (every set's: checked above)
                                "symmetrize": settings[0]["symmetrize"], "wave_gain": settings[0]["wave_gain"],
                                "bodies": len(rows), "sets": sources,
                                "per_body_from": per_body_from and str(per_body_from)})
    return summary


def _per_body_columns(tables: list[list[dict]], sets: list[Path]) -> tuple[str, ...]:
    """:data:`PER_BODY` where every body of every set has its values, () where none has any; refused between."""
    counts = [sum(not any(missing_figure(row.get(c, "")) for c in PER_BODY) for row in table) for table in tables]
    if all(k == len(t) for k, t in zip(counts, tables, strict=True)):
        return PER_BODY
    if not any(counts):
        return ()
    partial = [f"{folder} has them on {k} of its {len(t)} bodies"
               for folder, k, t in zip(sets, counts, tables, strict=True) if k < len(t)]
    raise ValueError(f"--pool: per-body values on some bodies only ({'; '.join(partial)}): evaluate every body with "
                     "--per-body N (N = the set's body count), take them from an earlier pooled table "
                     "(--per-body-from), or pool evaluations without --per-body")


def _pooled_summary(v: dict[str, np.ndarray]) -> list[dict]:
    """The pooled ``summary.csv`` of the columns ``v`` (each ``[bodies]``): the means, the mean command against the
    hand-set wave paired per body and as a ratio, with per-body columns the fractions of per-body control, and the
    fractions beyond their own gait."""
    n, own = len(v["open_loop"]), "per_body" in v
    summary = [summary_row("open loop (each body's own gait)", v["open_loop"]),
               summary_row("controller (stochastic)", v["controller"]),
               summary_row("controller (mean command)", v["mean_command"]),
               summary_row("hand-set travelling wave (mean command)", v["hand_set_wave"]),
               summary_row("paired per body: controller (mean command) minus the hand-set wave",
                           v["mean_command"] - v["hand_set_wave"], paired=True)]
    whose = [("controller (stochastic)", "controller"), ("controller (mean command)", "mean_command")]
    ratios = [("controller (mean command) over the hand-set wave", v["mean_command"].mean() / v["hand_set_wave"].mean())]
    if own:
        summary += [summary_row("per-body controllers (stochastic)", v["per_body"]),
                    summary_row("per-body controllers (mean command)", v["per_body_mean_command"])]
        ratios[:0] = [("fraction of per-body control (stochastic)", v["controller"].mean() / v["per_body"].mean()),
                      ("fraction of per-body control (mean command)",
                       v["mean_command"].mean() / v["per_body_mean_command"].mean())]
        whose += [("per-body controllers (stochastic)", "per_body"),
                  ("per-body controllers (mean command)", "per_body_mean_command")]
    summary += [_ratio_row(what, ratio, n) for what, ratio in ratios]
    return summary + [_beyond_gait(who, v[key], v["open_loop"]) for who, key in whose]


def main(argv: list[str] | None = None) -> None:
    import argparse

    p = argparse.ArgumentParser(prog="python -m lab.heldout", description=pool.__doc__.split("\n")[0])
    p.add_argument("--pool", nargs="+", required=True, type=Path, help="--evaluate output folders to pool")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--per-body-from", type=Path, default=None,
                   help="a pooled table of the same sets (same order) whose per-body columns to take (for sets "
                        "evaluated without --per-body): its folder or bodies CSV, e.g. "
                        "lab/results/control_student/heldout93/student64_gen3_bodies.csv")
    args = p.parse_args(argv)
    pool(args.pool, args.out, args.per_body_from)


if __name__ == "__main__":
    main()
