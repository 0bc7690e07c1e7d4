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

    python -m lab.control --minutes 28 --out lab/results/control_walker
    python -m lab.control --gait lab/results/control_walker      # the trained gait, looked at
    python -m lab.control --evaluate runs/control_steering --out lab/results/control_steering  # an app run

``--evaluate RUN`` evaluates a control or co-design run of ``freeform-train`` (``experiment=control_* |
codesign_*``): its untrained and last policy on fresh headings, against open-loop gaits (``evaluate_run``), and
writes the last controller as ``controller.pt`` beside the results.

Zero-shot, on bodies of your own (``lab.heldout.evaluate_bodies``)::

    python -m lab.control --evaluate PATH --bodies BODIES.npy --headings fixed|random|any \
        --eval-episodes N --out DIR

PATH a control run's directory, a results folder holding ``controller.pt``, or that file; BODIES a ``.npy`` of
uint8 grids ``[M, ρ, ρ, ρ]`` (0 empty, 1 passive, 2 and 3 muscles in anti-phase). Writes ``DIR/bodies.csv`` and
``DIR/summary.csv``: open loop, the controller, the controller with its sensed channels zeroed, an untrained one,
the hand-set travelling wave; ``--per-body N`` adds each of the first N bodies' own controller (per-body control,
trained once and cached) and the fraction of it the controller reaches.

Writes ``curve.csv`` (per epoch: wall seconds, training return, the update's statistics), ``summary.csv``,
``control_walker.png``, ``walker.npy`` and ``controller.pt`` into ``--out``. ``--gait DIR`` replays DIR's controller
(its mean command) on the walker: ``freeform-control watch`` (``gait.gif``, ``gait.json``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments.common import summary_row, write_rows
from freeform.agents import PPO, ConvController, PPOConfig
from freeform.agents.controller_file import CONTROLLER_FILE, read_controller, save_controller
from freeform.agents.networks.controller_heads import HandSetWave
from freeform.envs.control import (
    HEADINGS,
    ControlConfig,
    ControlEnv,
    open_loop_displacement,
)
from freeform.envs.symmetry import GROUPS
from freeform.envs.untrained import DesignBodies, untrained_walker
from freeform.sim import SimConfig
from lab.heldout import Evaluation, PerBody, evaluate_bodies

RHO, MATERIALS, DESIGN_STEPS, BUNDLE = 8, 4, 20, 2  # the locomotion CPU demo's design setting (locomotion_cpu)


def gait(directory: Path, fps: float = 40.0) -> dict:
    """``directory``'s trained controller on its walker: ``freeform-control watch DIR/controller.pt DIR/walker.npy
    --out DIR`` (``gait.gif``, ``gait.json``)."""
    from freeform.control.cli import main as control

    control(["watch", str(directory / CONTROLLER_FILE), str(directory / "walker.npy"), "--out", str(directory),
             "--fps", str(fps)])
    return json.loads((directory / "gait.json").read_text())


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
        return control_env(cfg, torch.device("cpu"), (0, cfg.env.num_envs), seed, shared_headings=False)
    return control_env(cfg, torch.device("cpu"), (0, cfg.env.num_envs), seed, bodies=env.grids, box=env.box,
                       shared_headings=False)


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
        write_rows(out / name, table)
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


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m lab.control", description=__doc__.split("\n\n")[0])
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
    p.add_argument("--symmetrize", choices=GROUPS, default=None,
                   help="with --bodies: evaluate the controller averaged over this group of the ground's turns and "
                        "mirrors (freeform.agents.networks.group_average): 'ground' along random headings in the world's "
                        "frame, 'mirror' where a wave runs along x")
    p.add_argument("--wave-gain", type=float, default=None, metavar="G",
                   help="with --bodies: the controller's wave head played at gain G (the hand-set wave plus G x what "
                        "it learnt: freeform.agents.networks.controllers.with_wave_gain); default: the file's own")
    args = p.parse_args(argv)
    if args.bodies and not args.evaluate:
        p.error("--bodies needs --evaluate PATH (the controller to evaluate)")
    if (args.per_body or args.symmetrize or args.wave_gain is not None) and not args.bodies:
        p.error("--per-body, --symmetrize and --wave-gain need --evaluate PATH --bodies BODIES.npy")
    if args.evaluate and args.bodies:
        per = PerBody(args.per_body, args.per_body_preset, args.per_body_copies, tuple(args.per_body_set),
                      Path(args.per_body_cache), args.per_body_run and Path(args.per_body_run)) if args.per_body else None
        wave = HandSetWave(args.wave_k, args.wave_amplitude) if args.wave_k is not None else None
        how = Evaluation(episodes=args.eval_episodes, headings=args.headings, seed=args.seed,
                         symmetrize=args.symmetrize, wave_gain=args.wave_gain)
        evaluate_bodies(Path(args.evaluate), Path(args.bodies), Path(args.out), how, per, wave)
        return
    if args.evaluate:
        evaluate_run(Path(args.evaluate), args.eval_episodes, Path(args.out))
        return
    if args.gait:
        gait(Path(args.gait))
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
    write_rows(out / "curve.csv", curve)
    write_rows(out / "summary.csv", rows)
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
