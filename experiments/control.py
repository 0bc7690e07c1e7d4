"""Closed-loop control on the CPU (issue 29's first learning demo): a walker's open-loop sine gait against a
controller that PPO trains on the same body.

The walker: the best of ``--candidates`` bodies an untrained design policy builds (the locomotion CPU demo's
setting, ``experiment=locomotion_cpu``: ρ = 8, three materials, 20 design steps), scored by its open-loop gait. Its open-loop figure is the centre of
mass's move along +x over the control window (``control.burn_in`` to ``burn_in + duration``: the gait's sine from
t = 0, as every open-loop body). The controller: :class:`freeform.agents.ConvController` trained by PPO on
``--envs`` copies of the walker in a :class:`freeform.envs.control.ControlEnv` (the same window: zero commands
during the burn-in, then one command per voxel every ``control.period``), reward = the move along +x per control
step, for ``--minutes`` of wall time. Evaluated before and after training over ≥ 256 episodes of the stochastic
policy (99 % bands; the copies differ only by the policy's noise) and once with its deterministic mode.

    python -m experiments.control --minutes 28 --out docs/results/control_walker
    python -m experiments.control --gait docs/results/control_walker      # the trained gait, looked at
    python -m experiments.control --evaluate runs/control_steering --out docs/results/control_steering  # an app run

``--evaluate RUN`` evaluates a control or co-design run of ``freeform-train`` (``experiment=control_* |
codesign_*``): its untrained and last policy on fresh headings, against open-loop gaits (``evaluate_run``), and
writes the last controller as ``controller.pt`` beside the results.

Zero-shot, on bodies of your own (``evaluate_bodies``)::

    python -m experiments.control --evaluate PATH --bodies BODIES.npy --headings fixed|random|any \
        --eval-episodes N --out DIR

PATH a control run's directory, a results folder holding ``controller.pt``, or that file; BODIES a ``.npy`` of
uint8 grids ``[M, ρ, ρ, ρ]`` (0 empty, 1 passive, 2 and 3 muscles in anti-phase). Writes ``DIR/bodies.csv`` and
``DIR/summary.csv``: open loop, the controller, the controller with its sensed channels zeroed, an untrained one,
the hand-set travelling wave; ``--per-body N`` adds each of the first N bodies' own controller (per-body control,
trained once and cached) and the fraction of it the controller reaches.

Writes ``curve.csv`` (per epoch: wall seconds, training return, the update's statistics), ``summary.csv``,
``control_walker.png``, ``walker.npy`` and ``controller.pt`` into ``--out``. ``--gait DIR`` replays DIR's controller
(deterministic) on the walker, writes ``gait_closed_loop.gif`` and ``gait_open_loop.gif`` and ``gait.json``: how
high the centre of mass rises, how often the commands switch (their dominant frequency against the sine's 4 Hz),
how many sit at the clip — what to look at before believing a fast gait.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments.common import mean_band
from freeform.agents import PPO, ConvController, PPOConfig
from freeform.agents.controller_file import CONTROLLER_FILE, controller_for, read_controller, save_controller
from freeform.agents.controller_heads import DEFAULT_WAVE, HandSetWave
from freeform.agents.controllers import CONTROLLERS, ContextConvController, controller_step
from freeform.agents.networks import rebuild
from freeform.envs.control import (
    HEADINGS,
    ControlConfig,
    ControlEnv,
    open_loop_displacement,
    open_loop_moves,
)
from freeform.envs.untrained import DesignBodies, untrained_walker
from freeform.sim import SimConfig, Simulator

RHO, MATERIALS, DESIGN_STEPS, BUNDLE = 8, 4, 20, 2  # the locomotion CPU demo's design setting (locomotion_cpu)


@torch.no_grad()
def gait(directory: Path, fps: float = 40.0) -> dict:
    """Replay ``directory``'s trained controller (its mode) on the walker alone; GIFs of the closed- and open-loop
    gaits and figures of the commanded gait (``gait.json``)."""
    from freeform.render.gait import render_recording, simulate_gait
    from freeform.render.video import write_video

    body = torch.from_numpy(np.load(directory / "walker.npy"))
    saved = read_controller(directory / CONTROLLER_FILE)
    policy, sim, control = saved.controller, saved.sim or SimConfig(), saved.control
    env = ControlEnv(body, sim=sim, control=control, box=policy.box)
    com: list[float] = []
    state = None  # (a recurrent controller's, carried through the episode)

    def act(obs: torch.Tensor) -> torch.Tensor:  # the controller's mode, and the height of the centre of mass
        nonlocal state
        com.append(float(env.engine.sense().com[0, 2]))
        (mean, _, mask, _), state = controller_step(policy, obs, state)
        return (mean * mask).clamp(-1, 1)

    recording, c, total = env.record(act)
    L = sim.voxel_size
    write_video(directory / "gait_closed_loop.gif", render_recording(recording), fps=fps / 2)
    open_loop_sim = Simulator(replace(sim, burn_in=control.burn_in, duration=control.duration))
    write_video(directory / "gait_open_loop.gif", render_recording(simulate_gait(open_loop_sim, body.numpy()[0], fps)),
                fps=fps / 2)
    # c: the commands [steps, actuated voxels]
    spectrum = np.abs(np.fft.rfft(c - c.mean(0), axis=0)).mean(1)
    freqs = np.fft.rfftfreq(len(c), d=control.period)
    com_z = np.array(com) / L
    figures = {
        "displacement_x": total, "steps": control.steps, "period_s": control.period,
        "com_rise_max": float(com_z.max() - com_z[0]), "com_z_start": float(com_z[0]),
        "commands_at_clip": float((np.abs(c) > 0.99).mean()),
        "mean_abs_change_per_step": float(np.abs(np.diff(c, axis=0)).mean()),
        "dominant_frequency_hz": float(freqs[1:][np.argmax(spectrum[1:])]),
        "sine_frequency_hz": 1.0 / sim.temp_period,
    }
    (directory / "gait.json").write_text(json.dumps(figures, indent=1))
    return figures


@torch.no_grad()
def evaluation_episodes(ppo: PPO, env: Any, episodes: int, deterministic: bool = False) -> dict[str, Any]:
    """``episodes`` whole episodes from ``env``'s next ones (a ``ControlEnv`` or ``CodesignEnv``), of the policy's
    samples (which draw from PPO's generator) or its mode: their returns (the move along the heading, voxel
    lengths), headings (radians), bodies ``[E, ρ, ρ, ρ]`` and body metrics."""
    out: dict[str, list] = {"returns": [], "headings": [], "bodies": [], "metrics": []}
    while len(out["returns"]) * env.num_envs < episodes:
        obs, total, done = env.reset(), torch.zeros(env.num_envs), torch.zeros(env.num_envs, dtype=torch.bool)
        act = ppo.episode_actor(deterministic)  # (a recurrent policy's state starts with these episodes)
        while not bool(done.all()):
            heading = env.heading.copy()  # (the control stage's; the env draws the next episode's when it ends)
            obs, reward, done, info = env.step(act(obs))
            total += reward
        out["returns"].append(total.numpy())
        out["headings"].append(heading)
        out["bodies"].append(info.get("bodies", info["final_grids"]).cpu().numpy())
        out["metrics"].append({k: v.cpu().numpy() for k, v in info["metrics"].items()})
    return {"returns": np.concatenate(out["returns"])[:episodes], "headings": np.concatenate(out["headings"])[:episodes],
            "bodies": np.concatenate(out["bodies"])[:episodes],
            "metrics": {k: np.concatenate([m[k] for m in out["metrics"]])[:episodes] for k in out["metrics"][0]}}


def evaluation_env(cfg: Any, env: Any, seed: int) -> Any:
    """A control or co-design run's env for evaluation, seeded ``seed``: a co-design run designs fresh bodies; a
    control run's are its training env's ``env`` (not searched again), in the same box."""
    from freeform.run.build import control_env

    if cfg.control.codesign:
        return control_env(cfg, torch.device("cpu"), (0, cfg.env.num_envs), seed)
    return control_env(cfg, torch.device("cpu"), (0, cfg.env.num_envs), seed, bodies=env.grids, box=env.box)


def evaluate_run(run: Path, episodes: int, out: Path, bins: int = 8) -> list[dict]:
    """A control or co-design run of the app (``freeform-train experiment=control_* | codesign_*``) evaluated: its
    untrained (checkpoint 0) and its last policy, ``episodes`` stochastic episodes each on fresh headings (seed +
    10,000, the same for both), against the bodies' open-loop gaits along the same headings (a co-design run's:
    the designs each policy built). Writes ``summary.csv``, ``by_heading.csv`` (mean return per heading sector),
    ``metrics.csv`` (the bodies' seven metrics), ``curve.csv`` (the training return per epoch, from TensorBoard) and
    ``<run name>.png``."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from freeform.checkpoint import load_checkpoint
    from freeform.config import from_container
    from freeform.run.build import build

    out.mkdir(parents=True, exist_ok=True)
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    cfg = from_container(last["config"])
    env, ppo = build(cfg, torch.device("cpu"))
    control, codesign = cfg.control.episode(), cfg.control.codesign
    seed = cfg.seed + 10_000
    eval_env = evaluation_env(cfg, env, seed)
    rows, sectors, metrics = [], {}, []
    what = "design + controller" if codesign else "controller"
    for name, path in (("untrained", run / "checkpoints" / "epoch_000000.pt"), ("trained", run / "checkpoints" / "last.pt")):
        state = load_checkpoint(path)
        ppo.restore(state)
        eval_env.reset(seed=seed)
        result = evaluation_episodes(ppo, eval_env, episodes)
        headings = result["headings"]
        rows.append(summary_row(f"{what}, {name} ({state['ppo']['epoch']} epochs, stochastic)", result["returns"]))
        sectors[name] = result["returns"]
        print(f"{rows[-1]['what']}: {rows[-1]['mean']:.3f} ± {rows[-1]['band99']:.3f}", flush=True)
        metrics.append({"policy": name, **{k: float(v.mean()) for k, v in result["metrics"].items()}})
        if codesign or name == "trained":  # (a control run's bodies are the same for both)
            moved = open_loop_displacement(result["bodies"], cfg.sim, control, headings=headings,
                                           planar=control.headings == "any")
            label = f"open loop: the {name} policy's designs" if codesign else "open loop: the bodies' sine gaits"
            where = "in the plane" if control.headings == "any" else "along the same headings"
            rows.insert(len(rows) - 1, summary_row(f"{label} {where}", moved))
            sectors[f"open_loop_{name}" if codesign else "open_loop"] = moved
    sector = np.floor(np.mod(headings, 2 * np.pi) / (2 * np.pi / bins)).astype(int)
    by_heading = [{"sector_deg": f"{360 * k / bins:.0f}-{360 * (k + 1) / bins:.0f}", "n": int((sector == k).sum()),
                   **{name: float(v[sector == k].mean()) if (sector == k).any() else float("nan")
                      for name, v in sectors.items()}} for k in range(bins)]
    events = EventAccumulator(str(run), size_guidance={"scalars": 0})
    events.Reload()
    curve = [{"epoch": i + 1, "global_step": e.step, "episode_reward_mean": e.value}
             for i, e in enumerate(events.Scalars("charts/episode_reward_mean"))]
    for name, table in (("summary.csv", rows), ("by_heading.csv", by_heading), ("metrics.csv", metrics),
                        ("curve.csv", curve)):
        with open(out / name, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
    (out / "run.json").write_text(json.dumps({"run": str(run), "name": cfg.name, "episodes": episodes,
                                              "epochs": int(last["ppo"]["epoch"]), "control": vars(cfg.control)}, indent=1))
    saved = read_controller(run)  # the last policy's controller, self-contained (--evaluate DIR --bodies reads it)
    save_controller(out / CONTROLLER_FILE, saved.controller, saved.control, saved.sim)
    figure(curve, rows, out / f"{cfg.name}.png",
           ylabel=f"move {'in the plane' if control.headings == 'any' else 'along the heading'} in "
                  f"{control.duration:g} s (voxel lengths)")
    for row in rows:
        print(f"{row['what']}: {row['mean']:.3f} ± {row['band99']:.3f} (n = {row['n']})")
    return rows


SENSED = ("rel_x", "rel_y", "rel_z", "vel_x", "vel_y", "vel_z", "strain", "contact")
"""The observation's sensed channels: zeroed, a controller has only the body's shape, the task and the clock."""


def read_bodies(path: Path, materials: int) -> torch.Tensor:
    """The bodies of a ``.npy`` of integer grids ``[M, ρ, ρ, ρ]`` (or one ``[ρ, ρ, ρ]``) in the design env's
    materials (0 empty, 1 … ``materials``), as uint8, each reduced to its largest 6-connected component (the robot;
    its other pieces would fall apart from it). Malformed input is refused naming the body and the problem; no row is
    ever dropped."""
    from freeform.body import largest_component

    try:
        grids = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"--bodies {path}: not a .npy of grids ({e})") from e
    grids = grids[None] if grids.ndim == 3 else grids
    if grids.ndim != 4 or len(grids) == 0 or not grids.shape[1] == grids.shape[2] == grids.shape[3]:
        raise ValueError(f"--bodies {path}: grids must be [M, ρ, ρ, ρ] (M ≥ 1 cubes), got shape {list(grids.shape)}")
    if not (np.issubdtype(grids.dtype, np.integer) or grids.dtype == np.bool_):
        raise ValueError(f"--bodies {path}: grids must hold integer material indices (uint8), got {grids.dtype}")
    for i, grid in enumerate(grids):
        bad = np.unique(grid[(grid < 0) | (grid > materials)])
        if bad.size:
            raise ValueError(f"--bodies {path}: body {i} holds material {bad.tolist()}, allowed 0 (empty) … {materials}")
        if not grid.any():
            raise ValueError(f"--bodies {path}: body {i} is empty (no voxel: nothing to control)")
    return largest_component(torch.from_numpy(grids.astype(np.uint8)))


@dataclass
class PerBody:
    """``--per-body N``: per-body controllers for the first ``n`` bodies, trained by ``freeform-train
    experiment=<preset>`` (a bank: ``control.teachers=n``, ``copies`` environments per body, the evaluated
    controller's episode settings) or read from ``cache`` (a run directory named by the bodies and settings, resumed
    where a run stopped early)."""

    n: int
    preset: str = "control_teachers_cpu"
    copies: int = 4
    overrides: tuple[str, ...] = ()
    cache: Path = Path("runs/per_body")
    run: Path | None = None
    """A teacher run to read instead (``control.teachers`` = n, its bodies the first n given: checked)."""


def _hydra_value(value: Any) -> str:
    return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def per_body_bank(grids: torch.Tensor, per: PerBody, control: ControlConfig, sim: SimConfig) -> Any:
    """The bank of per-body controllers for ``grids[:per.n]`` (:class:`PerBody`), trained or read from the cache;
    its run's physics must be ``sim`` (the evaluated controller's)."""
    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint
    from freeform.config import compose, from_container
    from freeform.train import train

    if not 1 <= per.n <= len(grids):
        raise ValueError(f"--per-body {per.n}: must be in 1 … {len(grids)} (the bodies given)")
    bodies = grids[: per.n].numpy()
    if per.run is not None:
        return _teacher_run(per.run, bodies)
    episode = [f"control.{k}={_hydra_value(v)}" for k, v in vars(control).items() if k != "privileged_critic"]
    overrides = [f"control.teachers={per.n}", f"env.num_envs={per.n * per.copies}", *episode, *per.overrides]
    key = hashlib.sha1(bodies.tobytes() + "|".join([per.preset, *overrides]).encode()).hexdigest()[:12]
    run = per.cache / f"{per.preset}_{per.n}_{key}"
    run.mkdir(parents=True, exist_ok=True)
    np.save(run / "bodies.npy", bodies)
    cfg = compose(f"experiment={per.preset}", f"control.bodies={run / 'bodies.npy'}", *overrides,
                  "trainer.render_every=0", "trainer.progress=false")
    last = run / "checkpoints" / "last.pt"
    if not last.is_file() or int(load_checkpoint(last)["epoch"]) < cfg.trainer.epochs:
        print(f"per-body controllers: training {per.n} in {run} ({cfg.trainer.epochs} epochs)", flush=True)
        with torch.enable_grad():  # (called from the evaluation, which computes no gradients)
            train(cfg, run)  # (trainer.resume=auto continues a run that stopped early)
    payload = load_checkpoint(last)
    if ControlEnv.simulation(from_container(payload["config"]).sim, control) != ControlEnv.simulation(sim, control):
        raise ValueError(f"--per-body: the per-body controllers in {run} were trained with another sim section than "
                         "the evaluated controller's: give its sim.* values with --per-body-set")
    return bank_from_checkpoint(payload, str(run))


def _teacher_run(run: Path, bodies: np.ndarray) -> Any:
    """The bank of the teacher run ``run``, whose bodies (``freeform.run.build.teacher_bodies``) must be
    ``bodies``."""
    from freeform.agents.distill import bank_from_checkpoint
    from freeform.body import largest_component
    from freeform.checkpoint import load_checkpoint
    from freeform.config import from_container
    from freeform.run.build import teacher_bodies

    payload = load_checkpoint(run / "checkpoints" / "last.pt")
    bank = bank_from_checkpoint(payload, str(run))
    theirs = largest_component(teacher_bodies(run, from_container(payload["config"]), bank.teachers)).numpy()
    if bank.teachers != len(bodies) or not np.array_equal(theirs, bodies):
        raise ValueError(f"--per-body-run {run}: its {bank.teachers} teachers' bodies are not the first {len(bodies)} "
                         "bodies given (save them from its records: final_grids[:M])")
    return bank


class _BankOnBodies(torch.nn.Module):
    """A bank of per-body controllers acting on an evaluation env's rows: row r is body ``rows_body[r]``'s."""

    def __init__(self, bank: Any, teacher: torch.Tensor, box: tuple[int, ...]) -> None:
        super().__init__()
        from freeform.agents.teachers import TeacherBank

        k = bank.init_kwargs  # (built for the evaluation's box: the kinds that fit any box)
        self.bank = TeacherBank(**{**k, "controller": {**k["controller"], "box": tuple(box)}})
        self.bank.load_state_dict(bank.state_dict())
        self.teacher, self.distribution = teacher, self.bank.distribution

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.bank({"teacher": self.teacher, "policy": obs}))


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


@torch.no_grad()
def evaluate_bodies(source: Path, bodies: Path, out: Path, episodes: int, headings: str | None = None,
                    seed: int = 0, per_body: PerBody | None = None,
                    wave: HandSetWave | None = None) -> tuple[list[dict], list[dict]]:
    """Zero-shot evaluation of a saved controller (``source``: a ``controller.pt``, a folder holding one, or a
    control run's directory) on the bodies of ``bodies`` (:func:`read_bodies`), ``episodes`` stochastic episodes
    each, under the controller's own ``ControlConfig`` (``headings`` overrides its heading task). One env runs every
    body × episode once per group, the groups with the same headings (the same draws): the controller, the
    controller's mean command (deterministic: what it learned, without its exploration noise), the controller with
    its sensed channels zeroed (:data:`SENSED`: a controller that only replays the clock loses nothing), an untrained
    controller of the same architecture (seeded ``seed``), stochastic and its mean command (what the architecture
    does before learning: the open-loop gait for most heads, the hand-set travelling wave for a ``wave`` head), the
    hand-set wave's mean command whatever the controller's head (:func:`hand_set_wave`; with strokes), and with
    ``per_body`` each of the first N bodies' own controller (:class:`PerBody`, stochastic). The box is the one the
    controller trained in where the bodies fit it, else theirs (refused for the MLP, which fits one box).

    Writes ``out/bodies.csv`` (per body: its voxels and actuated voxels as simulated, its open-loop sine gait over
    the same window and headings, the controller's mean over its episodes and that mean's 99 % band, its mean
    command's, the untrained controller's, the hand-set wave's and the per-body controller's means) and
    ``out/summary.csv`` (the means over the bodies with 99 % bands across bodies, then paired differences per body
    — mean command minus open loop, stochastic minus untrained, mean command minus the untrained mean command —
    whose bands leave out the across-body spread; with ``per_body`` the controller and its own per-body controllers
    on the first N bodies, and the fraction of per-body control the controller reaches), and ``out/run.json``.
    Returns (the body rows, the summary rows)."""
    saved = read_controller(source)
    sim = saved.sim or SimConfig()
    grids = read_bodies(bodies, len(sim.materials))
    trained = tuple(saved.controller.box)
    saved = controller_for(saved.path, grids)  # (its own box where the bodies fit it; the MLP refused otherwise)
    control = replace(saved.control, headings=headings or saved.control.headings)
    control.validate()
    m, n, box = len(grids), episodes, tuple(saved.controller.box)
    controller = saved.controller.eval()
    torch.manual_seed(seed)
    untrained = rebuild(CONTROLLERS[saved.kind], controller.init_kwargs).eval()
    bank = per_body_bank(grids, per_body, saved.control, sim) if per_body is not None else None
    groups = [("controller", controller, False, True), ("mean_command", controller, False, False),
              ("zeroed", controller, True, True), ("untrained", untrained, False, True),
              ("untrained_mean_command", untrained, False, False)]
    blocks = len(groups) + (control.stroke_periods >= 1) + 2 * (bank is not None)  # (one block of rows a group)
    env = ControlEnv(grids.repeat_interleave(n, 0).repeat(blocks, 1, 1, 1), sim=sim, control=control, seed=seed,
                     box=box, first_env=np.tile(np.arange(m * n), blocks))
    if control.stroke_periods >= 1:
        groups.append(("hand_set_wave", hand_set_wave(env, controller, wave), False, False))
    if bank is not None:
        rows_body = torch.arange(m).repeat_interleave(n)
        own = _BankOnBodies(bank, torch.where(rows_body < per_body.n, rows_body, 0), box)
        groups += [("per_body", own, False, True), ("per_body_mean_command", own, False, False)]
    returns, obs, heading = _play(env, groups, control.steps, seed)
    moves = open_loop_moves(grids, sim, control)  # [M, 2]
    along = open_loop_displacement(grids.repeat_interleave(n, 0), sim, control, headings=heading[: m * n],
                                   planar=control.headings == "any", moves=np.repeat(moves, n, 0)).reshape(m, n)
    per_group = {name: returns[g].reshape(m, n) for g, (name, *_) in enumerate(groups)}
    if bank is not None:
        per_group["per_body"][per_body.n:] = per_group["per_body_mean_command"][per_body.n:] = np.nan
    rows = _body_rows(per_group, along.mean(1), obs[: m * n : n], env)
    summary = _summary(per_group, along.mean(1), saved.kind, seed, per_body.n if bank is not None else 0)
    _write(out, rows, summary, {"controller": str(saved.path), "kind": saved.kind, "bodies": str(bodies),
                                "body_count": m, "episodes_per_body": n, "box": list(box), "trained_box": list(trained),
                                "seed": seed, "control": vars(control),
                                "per_body": None if per_body is None else {**vars(per_body), "cache": str(per_body.cache)}})
    return rows, summary


def _play(env: ControlEnv, groups: list[tuple], steps: int, seed: int) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """One episode of every group ``(name, net, sensed channels zeroed, stochastic)`` on its block of ``env``'s
    rows. Returns the returns ``[G, rows]``, the last observation and the episode's headings."""
    sensed = [env.channels.index(c) for c in SENSED]

    def view(obs: torch.Tensor, zeroed: bool) -> torch.Tensor:
        if not zeroed:
            return obs
        obs = obs.clone()
        obs[:, sensed] = 0.0
        return obs

    generator = torch.Generator().manual_seed(seed)
    obs, total = env.reset(), torch.zeros(env.num_envs, dtype=torch.float64)
    states: list = [None] * len(groups)  # (a recurrent controller's, per group, carried through the episode)
    for _ in range(steps):
        heading = env.heading.copy()  # (the episode's; the env draws the next episode's at its end)
        actions = []
        for g, ((_, net, zeroed, stochastic), part) in enumerate(zip(groups, obs.chunk(len(groups)), strict=True)):
            outputs, states[g] = controller_step(net, view(part, zeroed), states[g])
            params = outputs[:3]
            noise = torch.randn(params[0].shape, generator=generator)  # (drawn for every group: the same streams)
            actions.append(net.distribution.sample(params, noise) if stochastic else net.distribution.mode(params))
        obs, reward, _, _ = env.step(torch.cat(actions))
        total += reward.double()
    return total.numpy().reshape(len(groups), -1), obs, heading


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


def _summary(per_group: dict[str, np.ndarray], open_loop: np.ndarray, kind: str, seed: int, n_own: int) -> list[dict]:
    """``summary.csv``: the means over the bodies (99 % bands across bodies), then the paired differences per body
    (each body against itself: same headings, same noise streams, so the across-body spread cancels), and with
    per-body controllers on the first ``n_own`` bodies the controller and theirs there and the fraction reached."""
    body = {name: v.mean(1) for name, v in per_group.items()}
    summary = [summary_row("open loop (each body's sine gait, same window and headings)", open_loop),
               summary_row(f"controller ({kind}, stochastic)", body["controller"]),
               summary_row(f"controller ({kind}, mean command)", body["mean_command"]),
               summary_row("controller, sensed channels zeroed (rel, vel, strain, contact)", body["zeroed"]),
               summary_row(f"untrained controller ({kind}, seed {seed}, stochastic)", body["untrained"]),
               summary_row(f"untrained controller ({kind}, seed {seed}, mean command)", body["untrained_mean_command"]),
               summary_row("paired per body: controller (mean command) minus open loop",
                           body["mean_command"] - open_loop),
               summary_row("paired per body: controller (stochastic) minus untrained (stochastic)",
                           body["controller"] - body["untrained"]),
               summary_row("paired per body: controller (mean command) minus untrained (mean command)",
                           body["mean_command"] - body["untrained_mean_command"]),
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
                    {**summary_row(f"fraction of per-body control ({how}): controller mean / per-body mean "
                                   f"({n_own} bodies)", np.array([yours.mean() / own.mean()])),
                     "band99": float("nan"), "n": n_own}]
    return summary


def _beyond_gait(who: str, moved: np.ndarray, open_loop: np.ndarray) -> dict:
    """The fraction of bodies that ``who`` moves further than their own open-loop gait (the band: the fraction's)."""
    return summary_row(f"fraction of bodies beyond their own gait: {who}", (moved > open_loop).astype(float))


def _write(out: Path, rows: list[dict], summary: list[dict], run: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, table in (("bodies.csv", rows), ("summary.csv", summary)):
        with open(out / name, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
    (out / "run.json").write_text(json.dumps(run, indent=1, default=str))
    for row in summary:
        print(f"{row['what']}: {row['mean']:.3f} ± {row['band99']:.3f} (n = {row['n']} bodies)")


def summary_row(name: str, values: np.ndarray) -> dict:
    mean, band = mean_band(values)
    return {"what": name, "n": len(values), "mean": float(mean), "band99": float(band),
            "low": float(mean - band), "high": float(mean + band)}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.control", description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=28.0, help="wall-time budget of the training")
    p.add_argument("--envs", type=int, default=64, help="copies of the walker trained at once")
    p.add_argument("--candidates", type=int, default=256)
    p.add_argument("--eval-episodes", type=int, default=256)
    p.add_argument("--hidden", type=int, default=16)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--log-std", type=float, default=-0.5, help="the controller's initial log σ (commands lie in [-1, 1])")
    p.add_argument("--burn-in", type=float, default=2.0,
                   help="seconds of settling before the window (2 s, as the locomotion demo: bodies have landed)")
    p.add_argument("--command-rate", type=float, default=None,
                   help="the most a command may change per second (ControlConfig.command_rate; default: any)")
    p.add_argument("--ramp", action="store_true",
                   help="ramp each new command over the period instead of jumping to it (ControlConfig.ramp)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/control_walker")
    p.add_argument("--gait", metavar="DIR", help="only replay DIR's trained controller and write its gait")
    p.add_argument("--evaluate", metavar="PATH",
                   help="only evaluate: a control run of freeform-train (its untrained and last policy, into --out), "
                        "or with --bodies any saved controller (a run's directory, a folder holding controller.pt, "
                        "or that file) on the given bodies")
    p.add_argument("--bodies", metavar="BODIES.npy",
                   help="with --evaluate: a .npy of uint8 grids [M, ρ, ρ, ρ] (0 empty, 1 passive, 2 and 3 muscles): "
                        "writes bodies.csv and summary.csv into --out (--eval-episodes episodes per body)")
    p.add_argument("--headings", choices=HEADINGS, default=None,
                   help="with --bodies: the heading task (default: the controller's own)")
    p.add_argument("--per-body", type=int, default=0, metavar="N",
                   help="with --bodies: also each of the first N bodies' own controller (trained by freeform-train "
                        "experiment=--per-body-preset as a bank of N teachers, or read from --per-body-cache): "
                        "bodies.csv gains per_body, the summary the fraction of per-body control reached")
    p.add_argument("--per-body-preset", default="control_teachers_cpu")
    p.add_argument("--per-body-copies", type=int, default=4, help="environments per body in the per-body training")
    p.add_argument("--per-body-set", action="append", default=[], metavar="KEY=VALUE",
                   help="an override of the per-body training (repeatable), e.g. trainer.epochs=40")
    p.add_argument("--per-body-cache", default="runs/per_body")
    p.add_argument("--per-body-run", default=None, metavar="RUN",
                   help="read the per-body controllers from this teacher run (control.teachers=N) instead")
    p.add_argument("--wave-k", type=float, default=None,
                   help="with --bodies: the hand-set wave's k (default: the controller's own wave, else 1.0)")
    p.add_argument("--wave-amplitude", type=float, default=1.0)
    args = p.parse_args(argv)
    if args.bodies and not args.evaluate:
        p.error("--bodies needs --evaluate PATH (the controller to evaluate)")
    if args.per_body and not args.bodies:
        p.error("--per-body needs --evaluate PATH --bodies BODIES.npy")
    if args.evaluate and args.bodies:
        per = PerBody(args.per_body, args.per_body_preset, args.per_body_copies, tuple(args.per_body_set),
                      Path(args.per_body_cache), args.per_body_run and Path(args.per_body_run)) if args.per_body else None
        wave = HandSetWave(args.wave_k, args.wave_amplitude) if args.wave_k is not None else None
        evaluate_bodies(Path(args.evaluate), Path(args.bodies), Path(args.out), args.eval_episodes, args.headings,
                        args.seed, per, wave)
        return
    if args.evaluate:
        evaluate_run(Path(args.evaluate), args.eval_episodes, Path(args.out))
        return
    if args.gait:
        print(json.dumps(gait(Path(args.gait)), indent=1))
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    sim, control = SimConfig(), ControlConfig(burn_in=args.burn_in, command_rate=args.command_rate, ramp=args.ramp)

    t0 = time.perf_counter()
    body, scores = untrained_walker(args.candidates, DesignBodies(RHO, MATERIALS, DESIGN_STEPS, BUNDLE), args.seed, sim,
                                    control)
    print(f"walker: {int((body > 0).sum())} voxels, open loop {scores.max():.3f} voxel lengths over "
          f"{control.duration} s (best of {len(scores)}; median {np.median(scores):.3f}) [{time.perf_counter() - t0:.0f} s]")
    np.save(out / "walker.npy", body.numpy())
    env = ControlEnv(body.expand(args.envs, -1, -1, -1).clone(), sim=sim, control=control, seed=args.seed)
    eval_env = ControlEnv(body.expand(args.envs, -1, -1, -1).clone(), sim=sim, control=control, seed=args.seed + 1)
    cfg = PPOConfig(lr=args.lr, gamma=0.99, gae_lambda=0.95, clip_param=0.2, kl_coeff=0.0, entropy_coeff=0.0,
                    num_sgd_iter=2, sgd_minibatch_size=512, rollout_steps=control.steps, grad_clip=0.5,
                    reward_norm=True, seed=args.seed)
    policy = ConvController(env.observation_shape[0], env.box, env.mask_channel, 0, args.hidden, args.log_std)
    ppo = PPO(env, policy, cfg)
    print(f"box {env.box}, {env.action_dim} cells, {int(env.action_mask[0].sum())} actuated; "
          f"{control.steps} control steps of {control.period} s per episode")
    rows = [summary_row("open loop (its sine gait, deterministic)", np.array([scores.max()]))]
    before = evaluation_episodes(ppo, eval_env, args.eval_episodes)["returns"]
    rows.append(summary_row("controller, untrained (stochastic)", before))
    print(f"untrained: {rows[-1]['mean']:.3f} ± {rows[-1]['band99']:.3f} [{time.perf_counter() - t0:.0f} s]", flush=True)

    curve, start = [], time.perf_counter()
    while time.perf_counter() - start < args.minutes * 60:
        stats = ppo.train_epoch()
        curve.append({"epoch": ppo.epoch, "wall_s": time.perf_counter() - start, **{k: stats[k] for k in (
            "episode_reward_mean", "approx_kl", "entropy", "action_std", "explained_variance", "time_rollout",
            "time_update")}})
        print(f"epoch {ppo.epoch}: return {stats['episode_reward_mean']:.3f}, σ {stats['action_std']:.3f}, "
              f"rollout {stats['time_rollout']:.1f} s, update {stats['time_update']:.1f} s", flush=True)
    save_controller(out / CONTROLLER_FILE, ppo.policy, control, sim)
    after = evaluation_episodes(ppo, eval_env, args.eval_episodes)["returns"]
    rows.append(summary_row(f"controller, trained {ppo.epoch} epochs (stochastic)", after))
    # (the copies are one body from one settled state: the mode's episode is one number)
    rows.append(summary_row("controller, trained (deterministic)",
                            evaluation_episodes(ppo, eval_env, eval_env.num_envs, deterministic=True)["returns"][:1]))
    for row in rows:
        print(f"{row['what']}: {row['mean']:.3f} ± {row['band99']:.3f} (n = {row['n']})")
    if not curve:
        raise SystemExit("no epoch ran within --minutes")
    with open(out / "curve.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(curve[0]))
        writer.writeheader()
        writer.writerows(curve)
    with open(out / "summary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "args.json").write_text(json.dumps(vars(args), indent=1))
    figure(curve, rows[:3], out / "control_walker.png")


def figure(curve: list[dict], rows: list[dict], path: Path,
           ylabel: str = "move along +x in 2 s (voxel lengths)") -> None:
    """The training return per epoch; open-loop rows as dashed lines, the policy's rows as points with their 99 %
    bands (untrained at epoch 0, trained at the last)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([r["epoch"] for r in curve], [r["episode_reward_mean"] for r in curve], color="k", lw=1,
            label="training return (mean of the batch)")
    lines, points = iter(("tab:red", "tab:orange", "tab:brown")), iter(("tab:grey", "tab:blue", "tab:green"))
    for row in rows:
        if row["what"].startswith("open loop"):
            ax.axhline(row["mean"], color=next(lines), ls="--", label=row["what"])
        else:
            x = 0 if "untrained" in row["what"] else curve[-1]["epoch"]
            ax.errorbar([x], [row["mean"]], yerr=[row["band99"]], fmt="o", color=next(points), capsize=3,
                        label=row["what"] + ", 99 % band")
    ax.set_xlabel("epoch")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=150)


if __name__ == "__main__":
    main()
