"""Co-design against its two baselines at equal simulated robot-seconds (issue 32), on flat locomotion.

Three runs of ``freeform-train``, each given the same budget of simulated robot-seconds:

* ``--codesign RUN``: ``experiment=codesign_locomotion_cpu`` — one PPO designs a body and then controls it; every
  episode settles its new body (``control.burn_in``) and controls it (``control.duration``).
* ``--open-loop RUN``: open-loop design RL — ``experiment=locomotion_cpu`` with the co-design episode's window
  (``sim.burn_in`` = ``control.burn_in``, ``sim.duration`` = ``control.duration``) and the centre of mass's move as
  the reward (``+task.options.measure=com``): the paper's method, each body moving by its sine gait.
* ``--two-stage RUN``: design, then control — a control run (``experiment=control_locomotion_cpu``) on the best
  designs of one epoch of a design run (``control.bodies=<design run>/records/epoch_E.npz control.top=K``); its
  budget is the design run's first E + 1 epochs plus its own.

A warm-started co-design run (``control.controller_init``), or ``--designed``'s frozen controller, is charged the
training behind its controller: ``--pretraining OVERRIDES`` (the control run one preset describes) and
``--pretraining-runs RUN...`` (run directories, each for the epochs its last checkpoint reached: a distilled
student's lineage of teacher and distillation runs).

Every method is scored the same way: its last policy's bodies (256 designs of the design policies; the two-stage
run's K bodies, cycled) in the co-design episode's window, stochastic policies as in training, 99 % bands. A
controller is scored by what it was trained for: its centre of mass's move along +x (``control.headings=fixed``),
or, with ``control.headings=any``, its distance moved in the plane — the figure an open-loop body is scored by (its
move in the plane in whichever direction its gait goes; a gait has no heading to choose, so +x would score it 0 on
average). The seven body metrics of each method's bodies (the paper's) go beside the scores.

    python -m lab.codesign --codesign runs/codesign_locomotion --open-loop runs/open_loop_locomotion \
        --two-stage runs/two_stage_control --out lab/results/codesign_vs_baselines

Writes ``summary.csv`` (method, robot-seconds, score with its band, what the score is), ``metrics.csv``,
``run.json`` and ``codesign_vs_baselines.png``.
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from experiments.common import mean_band, read_rows, write_rows

METRICS = ("volume", "surface_ratio", "passive_ratio", "lcc_ratio", "substructures", "symmetry", "compressibility")


def _last(run: Path) -> tuple[Any, dict]:
    from freeform.checkpoint import load_checkpoint
    from freeform.config import from_container

    last = load_checkpoint(run / "checkpoints" / "last.pt")
    return from_container(last["config"]), last


def design_stage(control_cfg: Any) -> tuple[Path, int] | None:
    """The design run and epoch count behind a two-stage control run's bodies (``control.bodies`` naming
    ``<run>/records/epoch_E.npz``: E + 1 epochs of design), or None when its bodies came from elsewhere."""
    source = Path(str(control_cfg.control.bodies))
    match = re.fullmatch(r"epoch_(\d+)\.npz", source.name)
    if match is None or source.parent.name != "records":
        return None
    return source.parent.parent, int(match.group(1)) + 1


def robot_seconds(cfg: Any, epochs: int) -> float:
    """The simulated robot-seconds ``epochs`` epochs of a run cost. An epoch plays ``agent.rollout_steps`` steps an
    environment, whole episodes of the run's env (None: one; the teacher and distillation presets play 4). A
    co-design or design episode simulates its body through its window (settling included; a design scored by a
    controller, through that controller's episode); a control episode only the control window, each body settling
    once, when the env is built — every environment's copy, a body repeated over environments included — and
    restored from that state at every episode; a population run's, every cohort it played settled once
    (``freeform.envs.population.robot_seconds``)."""
    from freeform.config import episode_steps

    envs, episode = cfg.env.num_envs, episode_steps(cfg)
    # episodes each environment played (whole ones in a control run, whose rollout config.py keeps a multiple of
    # its episode; a design rollout may end mid-episode, which counts its fraction)
    episodes = epochs * (cfg.agent.rollout_steps or episode) / episode
    if cfg.control is None:
        if cfg.task.name == "controlled_locomotion":  # design after control: each design a controlled episode
            from freeform.agents.controller_file import read_controller

            scored = read_controller(cfg.task.options["controller"]).control
            return episodes * envs * (scored.burn_in + scored.duration)
        return episodes * envs * (cfg.sim.burn_in + cfg.sim.duration)  # open-loop design RL
    control = cfg.control
    if control.codesign:
        return episodes * envs * (control.burn_in + control.duration)
    if control.bodies == "population":
        from freeform.envs.population import robot_seconds as stream_seconds

        return stream_seconds(round(episodes), envs, control, cfg.seed)
    return episodes * envs * control.duration + envs * control.burn_in


def pretraining_seconds(overrides: list[str] | None, runs: list[Path] | None = None) -> tuple[float, str]:
    """The robot-seconds behind a frozen or warm-start controller, and what they count: the control run that the
    app's ``overrides`` describe (its preset, seed and epochs), plus every run directory in ``runs`` charged the
    epochs its last checkpoint reached — a distilled student's lineage (the population controller, each
    generation's teachers and distillation) is such a list of runs, none of which one preset describes."""
    from freeform.config import compose

    seconds, what = 0.0, []
    if overrides:
        cfg = compose(*overrides)
        if cfg.control is None:
            raise SystemExit(f"--pretraining {' '.join(overrides)}: not a control run (no control section)")
        seconds, what = robot_seconds(cfg, cfg.trainer.epochs), [" ".join(overrides)]
    charged: set[Path] = set()
    origins: dict[Any, _Charged] = {}  # (a run's origin -> what is charged for it)
    for run, epochs, pooled in _lineage(runs or ()):
        if run.resolve() in charged:  # (a run named twice, or named and pooled: its rollouts happened once)
            raise SystemExit(f"--pretraining-runs: {run} is charged twice (named twice, or named beside a pooled "
                             "folder that holds its teachers)")
        charged.add(run.resolve())
        cfg, last = _last(run)
        epochs = int(last["ppo"]["epoch"] if epochs is None else epochs)
        name = f"{run} ({epochs} epochs{f', pooled in {pooled}' if pooled else ''})"
        # A copied run directory (trained on from where it was copied) shares its first epochs with the original:
        # one origin is charged once, for the most epochs any copy of it reached — exact where one of them stopped
        # where the copy was made (a bank copied and trained on); two branches both trained past the copy would
        # each have rolled out their own epochs after it, and the shorter branch's are not charged.
        origin = _origin(run) or run.resolve()
        before = origins.get(origin)
        if before is not None and epochs <= before.epochs:
            what.append(f"{name}: the same run as {before.run} (copied), charged there")
            continue
        if before is not None:  # (this copy reached further: charged instead, the other's entry says so)
            what[before.entry] += f": the same run as {run} (copied), charged there"
        origins[origin] = _Charged(robot_seconds(cfg, epochs), epochs, str(run), len(what))
        what.append(name)
    seconds += sum(charged_run.seconds for charged_run in origins.values())
    return seconds, " + ".join(what) if what else "not counted"


class _Charged(NamedTuple):
    """What :func:`pretraining_seconds` charges for one run origin: its robot-seconds at the most epochs any copy
    reached, those epochs, the run charged and its entry in the description."""

    seconds: float
    epochs: int
    run: str
    entry: int


def _origin(run: Path) -> tuple[str, ...] | None:
    """What identifies the run that ``run`` is (or was copied from): the ``run_id`` its ``run_info.json`` records,
    which a copy keeps and a resume leaves alone — or, for runs from before it was recorded, their start time (to
    the second), host and command, which two runs of one process started within a second share; None without
    one."""
    info = run / "run_info.json"
    if not info.is_file():
        return None
    record = json.loads(info.read_text())
    if record.get("run_id"):
        return (str(record["run_id"]),)
    return (str(record.get("start_time")), str(record.get("hostname")), json.dumps(record.get("command")))


def _lineage(runs: Iterable[Path]) -> Iterator[tuple[Path, int | None, Path | None]]:
    """Each run to charge, the epochs to charge it (None: its last checkpoint's) and the pooled folder it came
    through: a pooled teacher folder (``freeform.run.teacher_runs``) stands for the runs it pooled, each at the
    epoch its teachers were taken (its own checkpoint is a copy: nothing was rolled out for it)."""
    from freeform.run.teacher_runs import POOLED

    for run in runs:
        if (run / POOLED).is_file():
            for source in json.loads((run / POOLED).read_text())["sources"]:
                src = _run_of(source["run"])  # (a pooled source may be named by one of its checkpoints)
                if (src / POOLED).is_file():  # (a pool of pools: charged by what the inner one pooled)
                    yield from _lineage([src])
                elif not (src / "checkpoints" / "last.pt").is_file():
                    raise SystemExit(f"--pretraining-runs {run}: it pooled {src}, which has no checkpoints/last.pt "
                                     "here (run from the directory it was pooled in, or name the runs themselves)")
                else:
                    yield src, source["epoch"], run
        elif not (run / "checkpoints" / "last.pt").is_file():
            raise SystemExit(f"--pretraining-runs {run}: no checkpoints/last.pt and no {POOLED} (a freeform-train "
                             "run directory, or a pooled teacher folder?)")
        else:
            yield run, None, None


def _run_of(path: str) -> Path:
    """A run's directory from its directory or one of its checkpoints (``<run>/checkpoints/*.pt``)."""
    p = Path(path).resolve()
    return p.parent.parent if p.suffix == ".pt" and p.parent.name == "checkpoints" else p


def warm_start_name(path: str) -> str:
    """How a table names the controller a run started from: the population controller's folder or zoo name as
    before, else the folder (or file, or zoo name) ``control.controller_init`` names."""
    where = _run_of(path)  # (a run's checkpoint names its run; a controller.pt, its folder)
    name = where.parent.name if where.suffix == ".pt" else where.name
    return "the population controller" if name in ("control_population", "population") else name


def gaits(grids: Any, sim: Any, window: Any, headings: np.ndarray | None = None,
          moves: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """Bodies moved by their open-loop sine gaits in ``window`` (a ``ControlConfig``; or their ``moves`` ``[N, 2]``,
    ``open_loop_moves``) and what the score is: the move in the plane, whichever way (a gait has no heading to
    choose), or on a steering task (``headings "random"``) the move along ``headings [N]`` — the controllers'
    headings, or fresh uniform draws."""
    from freeform.envs.control import open_loop_displacement, open_loop_moves

    moves = open_loop_moves(grids, sim, window) if moves is None else moves
    if window.headings != "random":
        return open_loop_displacement(grids, planar=True, moves=moves), "move in the plane, sine gait"
    if headings is None:
        headings = np.random.default_rng(10_000).uniform(0.0, 2 * np.pi, len(grids))
    return open_loop_displacement(grids, headings=headings, moves=moves), "move along its heading, sine gait"


def _metrics(info: dict) -> dict[str, np.ndarray]:
    return {k: v.double().cpu().numpy() for k, v in info["metrics"].items()}


@torch.no_grad()
def last_designs(run: Path, episodes: int) -> tuple[Any, dict, dict]:
    """A design run's config, last checkpoint and the final ``info`` of ``episodes`` designs of its last policy,
    sampled as in training, on a design env seeded apart from training's (``cfg.seed + 10_000``)."""
    from freeform.run.build import build, design_env

    cfg, last = _last(run)
    _, ppo = build(cfg, torch.device("cpu"))
    ppo.restore(last)
    env = design_env(cfg, torch.device("cpu"), episodes, cfg.seed + 10_000)
    obs, done = env.reset(), torch.zeros(episodes, dtype=torch.bool)
    while not bool(done.all()):
        obs, _, done, info = env.step(ppo.act(obs))
    return cfg, last, info


@torch.no_grad()
def open_loop_designs(run: Path, episodes: int, window: Any) -> dict[str, Any]:
    """``episodes`` designs of an open-loop design run's last policy (sampled as in training), moved by their sine
    gaits in ``window`` (a ``ControlConfig``): the score (:func:`gaits`), the move along +x, and the body metrics."""
    from freeform.envs.control import open_loop_moves

    cfg, last, info = last_designs(run, episodes)
    grids = info["final_grids"].cpu().numpy()
    moves = open_loop_moves(grids, cfg.sim, window)  # (simulated once: the score and the move along +x)
    score, kind = gaits(grids, cfg.sim, window, moves=moves)
    return {"score": score, "kind": kind, "along_x": moves[:, 0], "metrics": _metrics(info),
            "epochs": int(last["ppo"]["epoch"]), "cfg": cfg, "grids": grids}


@torch.no_grad()
def controlled(run: Path, episodes: int) -> dict[str, Any]:
    """A co-design or control run's last policy: ``episodes`` episodes on fresh episodes of its own env (a co-design
    run designs every one), the move along +x, and the bodies' metrics."""
    from freeform.run.build import build
    from lab.control import evaluation_env, evaluation_episodes

    cfg, last = _last(run)
    env, ppo = build(cfg, torch.device("cpu"))
    ppo.restore(last)
    seed = cfg.seed + 10_000
    eval_env = evaluation_env(cfg, env, seed)
    eval_env.reset(seed=seed)
    result = evaluation_episodes(ppo, eval_env, episodes)
    return {"score": result["returns"], "metrics": result["metrics"], "epochs": int(last["ppo"]["epoch"]),
            "cfg": cfg, "bodies": result["bodies"], "headings": result["headings"]}


@torch.no_grad()
def designed_for_controller(run: Path, episodes: int, window: Any) -> dict[str, Any]:
    """``episodes`` designs of a design-after-control run's last policy (``task.name=controlled_locomotion``,
    sampled as in training): scored by its task (the frozen controller driving each one, the move in the plane) and
    by their own sine gaits in ``window`` (:func:`gaits`), with the body metrics."""
    from freeform.run.build import build_task

    cfg, last, info = last_designs(run, episodes)
    grids = info["final_grids"].cpu()
    task = build_task(cfg, torch.device("cpu"))
    score = task.reward(grids, bodies=info["bodies"].cpu()).numpy()
    gait, kind = gaits(grids.numpy(), cfg.sim, window)
    return {"score": score, "gaits": gait, "gait_kind": kind, "metrics": _metrics(info),
            "epochs": int(last["ppo"]["epoch"]), "cfg": cfg, "task": task, "grids": grids.numpy()}


def result_diversity(result: dict) -> dict[str, float]:
    """A method's designs' ``distance`` (mean pairwise fraction of cells that differ) and ``distinct`` count
    (``freeform.body.diversity``): a co-design that collapses onto one body shows here."""
    from freeform.body import diversity

    grids = result.get("grids", result.get("bodies"))
    if grids is None or len(grids) < 2:
        return {"distance": float("nan"), "distinct": float("nan")}
    return diversity(torch.from_numpy(np.ascontiguousarray(np.asarray(grids))))


# a frozen controller's episodes (its fresh headings) are seeded apart from the evaluation episodes' (seed + 10_000)
FROZEN_EPISODES_SEED = 20_000


def warm_start_task(cfg: Any) -> Any:
    """The controller a co-design run started from (``control.controller_init``), frozen, as a task that scores
    designs by its mean command in its own episode, along the run's headings (fresh draws where they are random)."""
    from freeform.agents.controller_file import read_controller
    from freeform.envs.tasks import ControlledLocomotionTask

    return ControlledLocomotionTask(read_controller(cfg.control.controller_init), sim=cfg.sim, headings=cfg.control.headings,
                                    seed=cfg.seed + FROZEN_EPISODES_SEED)


def trained_for(control: Any) -> str:
    """What a controller's score is, from its run's ``control.headings``."""
    return {"fixed": "move along +x, controlled", "any": "move in the plane, controlled",
            "random": "move along its heading, controlled"}[control.headings]


def adapted_rows(run: Path, designs: dict[str, tuple[dict, float]]) -> list[tuple[str, dict, float, str]]:
    """The rows of an ``--adapted`` control run (one started from the frozen controller): its controller driving
    the designs it was adapted to (``control.designer``: one of ``designs``, name → (result, budget before the
    adaptation)), or, trained on untrained bodies (its control), every set of designs, along its own headings;
    the budget adds its own. Rows: (method, result, robot-seconds, what the score is)."""
    from freeform.agents.controller_file import read_controller
    from freeform.envs import ControlledLocomotionTask

    cfg, last = _last(run)
    epochs = int(last["ppo"]["epoch"])
    adapted = cfg.control.designer
    chosen = [name for name, (result, _) in designs.items()
              if adapted is None or _run_of(adapted) == _run_of(str(result["run"]))]
    if not chosen:
        raise SystemExit(f"--adapted {run}: adapted to the designs of {adapted}, which are not among this "
                         f"comparison's ({', '.join(designs)})")
    task = ControlledLocomotionTask(read_controller(run), sim=cfg.sim, headings=cfg.control.headings,
                                    seed=cfg.seed + FROZEN_EPISODES_SEED)
    rows = []
    for name in chosen:
        result, budget = designs[name]
        how = (f"adapted to them ({epochs} epochs on their stream)" if adapted is not None else
               f"trained {epochs} more epochs on untrained bodies")
        rows.append((f"  {name}, the controller {how}", {**result, "score": task.reward(
            torch.from_numpy(np.asarray(result["grids"]))).numpy(), "epochs": epochs},
            budget + robot_seconds(cfg, epochs), trained_for(cfg.control)))
    return rows


def compare(codesign: Path | None, open_loop: Path, two_stage: Path | None, episodes: int, out: Path,
            designed: Path | None = None, pretraining: list[str] | None = None,
            adapted: list[Path] | None = None, pretraining_runs: list[Path] | None = None) -> list[dict]:
    """Every method given against open-loop design RL (module docstring); ``designed``: a design-after-control run,
    its budget its design epochs' plus the pretraining's (``pretraining``: that run's app overrides;
    ``pretraining_runs``: run directories charged too, :func:`pretraining_seconds`);
    ``adapted``: control runs started from that controller (``control.controller_init``), whose controllers drive
    the same designs, their own epochs added to the budget."""
    before, what = pretraining_seconds(pretraining, pretraining_runs)  # (refuses a bad run before anything is written)
    out.mkdir(parents=True, exist_ok=True)
    rows, metrics, runs = [], [], {}

    def add(method: str, result: dict, budget: float, score: str, extra: dict | None = None) -> None:
        mean, band = mean_band(np.asarray(result["score"], np.float64))
        rows.append({"method": method, "robot_seconds": round(budget, 3), "epochs": result["epochs"],
                     "n": len(result["score"]), "mean": float(mean), "band99": float(band), "score": score,
                     **(extra or {})})
        metrics.append({"method": method, **{k: float(np.mean(result["metrics"][k])) for k in METRICS},
                        **result_diversity(result)})
        print(f"{method}: {mean:.3f} ± {band:.3f} ({score}; {budget:,.0f} robot-s)", flush=True)

    from freeform.envs.control import ControlConfig

    ol_cfg, _ = _last(open_loop)

    def sine_window(headings: str) -> ControlConfig:
        """Where every sine gait moves: the open-loop run's own window (its settling, then its evaluation: what it
        trained for), along a co-design run's headings where one is given."""
        return ControlConfig(burn_in=ol_cfg.sim.burn_in, duration=ol_cfg.sim.duration, headings=headings)

    window = sine_window("any")
    frozen = None  # a warm-started co-design run's first controller, as a task
    if codesign is not None:
        co = controlled(codesign, episodes)
        window = sine_window(co["cfg"].control.headings)
        runs["codesign"] = str(codesign)
        warm = co["cfg"].control.controller_init is not None  # (its controller's training is its budget too)
        if warm:
            runs["pretraining"] = what
        budget = robot_seconds(co["cfg"], co["epochs"]) + (before if warm else 0.0)
        name = f"co-design from {warm_start_name(co['cfg'].control.controller_init)}" if warm else "co-design"
        add(f"{name} (one PPO: body, then controller)", co, budget, trained_for(co["cfg"].control),
            {"pretraining_robot_seconds": round(before, 3)} if warm else None)
        moved, kind = gaits(co["bodies"], co["cfg"].sim, window, co["headings"])
        add("  its designs, open loop", {**co, "score": moved}, budget, kind)
        if warm:  # what the joint update added to the controller: the same designs under the warm start, frozen
            frozen = warm_start_task(co["cfg"])
            add("  its designs, driven by the warm-start controller (frozen)",
                {**co, "score": frozen.reward(torch.as_tensor(co["bodies"])).numpy()}, budget,
                trained_for(co["cfg"].control))

    ol = open_loop_designs(open_loop, episodes, window)
    runs["open_loop"] = str(open_loop)
    add("open-loop design RL (the paper's)", ol, robot_seconds(ol["cfg"], ol["epochs"]), ol["kind"],
        {"along_x_mean": float(ol["along_x"].mean())})

    # the designs a control run started from the frozen controller may drive (--adapted), with their budgets
    designs = {"open-loop design RL's designs": ({**ol, "run": open_loop},
                                                 before + robot_seconds(ol["cfg"], ol["epochs"]))}
    if frozen is not None and designed is None:  # (--designed adds this row for its own controller)
        add("open-loop design RL's designs, driven by the warm-start controller (frozen)",
            {**ol, "score": frozen.reward(torch.from_numpy(ol["grids"])).numpy()},
            before + robot_seconds(ol["cfg"], ol["epochs"]), trained_for(co["cfg"].control),
            {"pretraining_robot_seconds": round(before, 3)})

    if two_stage is not None:
        ts = controlled(two_stage, episodes)
        stage = design_stage(ts["cfg"])
        design_budget = 0.0
        if stage is not None:
            design_cfg, _ = _last(stage[0])
            design_budget = robot_seconds(design_cfg, stage[1])
            runs["two_stage_design"] = f"{stage[0]} (first {stage[1]} epochs)"
        runs["two_stage"] = str(two_stage)
        add(f"design, then control ({ts['cfg'].control.top} best designs)", ts,
            design_budget + robot_seconds(ts["cfg"], ts["epochs"]), trained_for(ts["cfg"].control))
        moved, kind = gaits(ts["bodies"], ts["cfg"].sim, window, ts["headings"])
        add("  its bodies, open loop", {**ts, "score": moved},
            design_budget + robot_seconds(ts["cfg"], ts["epochs"]), kind)

    if designed is not None:
        dc = designed_for_controller(designed, episodes, window)
        runs["designed_for_controller"] = str(designed)
        runs["pretraining"] = what
        budget = before + robot_seconds(dc["cfg"], dc["epochs"])
        frozen_name = warm_start_name(str(dc["cfg"].task.options["controller"]))
        add(f"design after control (frozen: {frozen_name})", dc, budget, "move in the plane, controlled",
            {"pretraining_robot_seconds": round(before, 3)})
        add("  its designs, open loop", {**dc, "score": dc["gaits"]}, budget, dc["gait_kind"])
        driven = dc["task"].reward(torch.from_numpy(ol["grids"])).numpy()  # (the paper's designs, then the controller)
        add("open-loop design RL's designs, driven by the same controller", {**ol, "score": driven},
            before + robot_seconds(ol["cfg"], ol["epochs"]), "move in the plane, controlled",
            {"pretraining_robot_seconds": round(before, 3)})
        designs = {"its designs": ({**dc, "run": designed}, budget), **designs}
    for run in adapted or ():
        runs[f"adapted: {run.name}"] = str(run)
        for method, result, seconds, score in adapted_rows(run, designs):
            add(method, result, seconds, score)

    for name, table in (("summary.csv", rows), ("metrics.csv", metrics)):
        write_rows(out / name, table)
    (out / "run.json").write_text(json.dumps({"runs": runs, "episodes": episodes,
                                              "window_s": [window.burn_in, window.duration]}, indent=1))
    figure(rows, metrics, out / "codesign_vs_baselines.png", window.duration)
    return rows


def figure(rows: list[dict], metrics: list[dict], path: Path, seconds: float) -> None:
    """The scores with their 99 % bands, one method a line (controlled: filled; the same bodies' open-loop gaits:
    hollow; indented names are the line above's bodies), the robot-seconds beside each, and the bodies' volume
    and passive ratio."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def short(method: str) -> str:  # a method, or (indented) another score of the bodies above
        return ("    " if method.startswith(" ") else "") + method.strip().split(" (")[0]

    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 1.2 + 0.42 * len(rows) + 0.3 * len(metrics)),
                                 gridspec_kw={"height_ratios": [len(rows), max(1, len(metrics))]})
    y = -np.arange(len(rows))
    for i, row in enumerate(rows):
        hollow = "sine gait" in row["score"]
        ax.errorbar([float(row["mean"])], [y[i]], xerr=[float(row["band99"])], fmt="o", capsize=4, color="k",
                    mfc="white" if hollow else "k")
    ax.set_yticks(y, [f"{short(r['method'])}  ({float(r['robot_seconds']):,.0f} robot-s)" for r in rows], fontsize=7)
    ax.set_xlabel(f"move in {seconds:g} s (voxel lengths), mean ± 99 % band")

    def what(hollow: bool) -> str:
        return " / ".join(sorted({r["score"].split(",")[0].replace("move ", "") for r in rows
                                  if ("sine gait" in r["score"]) == hollow}))

    ax.set_title(f"filled: controlled, {what(False)}; hollow: open loop, {what(True)}", fontsize=8)
    ax.axvline(0, color="0.7", lw=0.8)
    methods = [m for m in metrics if not m["method"].startswith(" ")]  # (an indented row repeats its bodies)
    names = [short(m["method"]) for m in methods]
    bx.barh(-np.arange(len(names)), [float(m["volume"]) for m in methods], color="0.6")
    for i, m in enumerate(methods):
        bx.text(float(m["volume"]), -i, f"  passive {float(m['passive_ratio']):.2f}, "
                f"largest part {float(m['lcc_ratio']):.2f}", va="center", fontsize=7)
    bx.set_yticks(-np.arange(len(names)), names, fontsize=7)
    bx.set_xlim(0, 2.1 * max(float(m["volume"]) for m in methods))
    bx.set_xlabel("body volume (voxels)")
    fig.tight_layout()
    fig.savefig(path, dpi=150)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--codesign", type=Path)
    p.add_argument("--open-loop", type=Path)
    p.add_argument("--two-stage", type=Path, default=None)
    p.add_argument("--designed", type=Path, default=None,
                   help="a design-after-control run (experiment=controlled_design_cpu): designs for a frozen controller")
    p.add_argument("--pretraining", nargs="+", default=None, metavar="OVERRIDE",
                   help="the app overrides of the control run behind --designed's controller (or --codesign's warm "
                        "start), whose robot-seconds its budget includes (e.g. experiment=control_population_cpu "
                        "seed=0)")
    p.add_argument("--pretraining-runs", type=Path, nargs="+", default=None, metavar="RUN",
                   help="run directories charged to the warm start's budget too, each for the epochs its last "
                        "checkpoint reached: a distilled student's lineage (teacher and distillation runs)")
    p.add_argument("--adapted", type=Path, nargs="+", default=None, metavar="RUN",
                   help="control runs started from the frozen controller (--designed's, or --codesign's warm start: "
                        "control.controller_init), e.g. adapted to designs (control.designer=DESIGNED or the "
                        "--open-loop run): their controllers drive those designs")
    p.add_argument("--episodes", type=int, default=256)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--replot", action="store_true", help="redraw the figure from --out's CSVs (no runs needed)")
    args = p.parse_args(argv)
    if args.replot:
        rows, metrics = (read_rows(args.out / name) for name in ("summary.csv", "metrics.csv"))
        seconds = json.loads((args.out / "run.json").read_text())["window_s"][1]
        figure(rows, metrics, args.out / "codesign_vs_baselines.png", seconds)
        return
    if args.open_loop is None or (args.codesign is None and args.designed is None):
        p.error("--open-loop and --codesign or --designed are required (or --replot)")
    if args.adapted and args.designed is None and args.pretraining is None and args.pretraining_runs is None:
        p.error("--adapted starts from a frozen controller: give --designed, or --codesign with --pretraining or "
                "--pretraining-runs")
    for run in (args.codesign, args.open_loop, args.two_stage, args.designed, *(args.adapted or ())):
        if run is not None and not (run / "checkpoints" / "last.pt").is_file():
            raise SystemExit(f"{run}: no checkpoints/last.pt (a freeform-train run directory?)")
    compare(args.codesign, args.open_loop, args.two_stage, args.episodes, args.out, args.designed, args.pretraining,
            args.adapted, args.pretraining_runs)


if __name__ == "__main__":
    main()
