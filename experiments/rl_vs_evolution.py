"""RL against evolution at an equal budget of scored designs: best-so-far and population-mean reward against the
number of designs scored (simulated, on the locomotion tasks), for PPO and every evolutionary baseline.

    freeform-train -m experiment=rl_vs_evolution_volume algo=ga,cmaes,grid_ga,ppo seed=0,1,2 trainer.threads=1
    python -m experiments.rl_vs_evolution runs/rl_vs_evolution_volume/<sweep> --out figures/rl_vs_evolution

Reads each run's design records (``freeform.records``) and config; runs are grouped by method (``algo.name``, plus
``dense(k)`` for a PPO run whose rewards are dense every k steps). A method's cost is the designs its task scored:
one per episode (sparse rewards; an evolutionary generation scores ``env.num_envs``), ``1 + (T − 1) // k`` per
episode with dense rewards every k steps (the partial bodies count too). Per method and epoch: the across-seed mean
and 99 % band (``experiments.common``) of the epoch's mean reward (smoothed ±2 epochs, as the paper's curves) and of
the best reward so far (not smoothed).

Writes ``rl_vs_evolution.png``/``.pdf`` (two panels: population mean, best so far), ``rl_vs_evolution.csv`` (the
curves) and ``rl_vs_evolution_summary.csv`` (each method at the comparison budget — ``--budget``, default the
largest number of designs every method reached: its population mean over the last 5 epochs and its best so far,
mean ± 99 % band over seeds, and the mean wall time of its runs), all with provenance lines.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from experiments import common

LAST_EPOCHS = 5
"""The population mean at the budget is each seed's mean over its last this many epochs (one epoch is noisy)."""

COLORS = {"ppo": "tab:blue", "ga": "tab:orange", "cmaes": "tab:green", "grid_ga": "tab:red"}
VARIANT_COLOR = "tab:purple"
"""A variant (``ppo+dense(k)``) drawn beside its base method: this colour, dashed."""


def method_of(config: dict[str, Any]) -> str:
    """The method a run's config names: ``algo.name`` (``ppo`` for runs made before the algo group), with
    ``+dense(k)`` when its rewards are dense every k design steps (``env.dense_every``, when the config has it)."""
    name = str((config.get("algo") or {}).get("name", "ppo"))
    every = (config.get("env") or {}).get("dense_every")
    return f"{name}+dense({every})" if every else name


def designs_per_episode(config: dict[str, Any]) -> int:
    """Designs the task scores per episode: 1 (the final body), or with dense rewards every k steps the partial bodies
    at steps k, 2k, … < T as well (``freeform.envs.dense.DenseDesignReward``)."""
    every = (config.get("env") or {}).get("dense_every")
    steps = int(config["env"]["steps"])
    return 1 + (steps - 1) // int(every) if every else 1


@dataclass
class Run:
    path: Path
    method: str
    epochs: np.ndarray  # [E]
    designs: np.ndarray  # [E] cumulative designs scored after each epoch
    mean: np.ndarray  # [E] the epoch's mean reward
    best: np.ndarray  # [E] the best reward so far
    wall_s: float  # start to last checkpoint (nan when unknown or resumed)


def _wall_seconds(run: Path, info: dict[str, Any]) -> float:
    from freeform.checkpoint import CHECKPOINT_DIR, LAST, load_checkpoint

    last = run / CHECKPOINT_DIR / LAST
    if info.get("resumes") or not last.is_file() or "start_time" not in info:
        return float("nan")
    saved = load_checkpoint(last).get("saved_at")
    if not saved:
        return float("nan")
    return (datetime.fromisoformat(saved) - datetime.fromisoformat(info["start_time"])).total_seconds()


def load_run(path: Path) -> Run:
    """A run's per-epoch mean and maximum reward and its cumulative cost, from its design records."""
    config = common.run_config(path)
    trial = common.load_trial(path)
    designs = np.cumsum(trial.episodes * designs_per_episode(config))
    return Run(path=path, method=method_of(config), epochs=trial.epochs, designs=designs, mean=trial.reward,
               best=np.maximum.accumulate(trial.reward_max), wall_s=_wall_seconds(path, trial.info))


@dataclass
class Method:
    name: str
    runs: list[Run]
    designs: np.ndarray  # [E] cumulative designs (mean over seeds: equal for every seed of a method)
    mean: common.Curve
    best: common.Curve


def group(runs: Sequence[Run]) -> list[Method]:
    """Runs grouped by method (PPO first, then the baselines by name), each with its across-seed curves."""
    names = sorted({r.method for r in runs}, key=lambda m: (not m.startswith("ppo"), m))
    methods = []
    for name in names:
        mine = [r for r in runs if r.method == name]
        epochs, means = common.align(mine, [r.mean for r in mine])
        _, best = common.align(mine, [r.best for r in mine])
        _, designs = common.align(mine, [r.designs for r in mine])
        methods.append(Method(name=name, runs=mine, designs=np.nanmean(designs, axis=0),
                              mean=common.across_trials(means, epochs),
                              best=common.across_trials(best, epochs, half_window=0)))
    return methods


@dataclass
class AtBudget:
    method: str
    designs: float
    mean: float
    mean_band: float
    best: float
    best_band: float
    wall_s: float
    seeds: int


def at_budget(method: Method, budget: float) -> AtBudget:
    """The method after its last epoch within ``budget`` designs: population mean (each seed's last
    ``LAST_EPOCHS`` epochs) and best so far, across-seed mean ± 99 % half-width."""
    means, bests, spent = [], [], []
    for r in method.runs:
        within = np.flatnonzero(r.designs <= budget)
        if not len(within):
            raise ValueError(f"--budget {budget:g}: run {r.path} ({r.method}) scores {r.designs[0]} designs in its "
                             f"first epoch alone")
        last = within[-1]
        means.append(np.nanmean(r.mean[max(0, last - LAST_EPOCHS + 1): last + 1]))
        bests.append(r.best[last])
        spent.append(float(r.designs[last]))
    m, mh = common.mean_band(np.asarray(means))
    b, bh = common.mean_band(np.asarray(bests))
    walls = [r.wall_s for r in method.runs if np.isfinite(r.wall_s)]
    return AtBudget(method=method.name, designs=max(spent), mean=float(m), mean_band=float(mh), best=float(b),
                    best_band=float(bh), wall_s=float(np.mean(walls)) if walls else float("nan"),
                    seeds=len(method.runs))


def verdict(rows: Sequence[AtBudget], field: str) -> str:
    """Which method leads on ``field`` (``mean`` or ``best``) and whether its band clears the runner-up's."""
    ranked = sorted(rows, key=lambda r: getattr(r, field), reverse=True)
    lead = ranked[0]
    if len(ranked) == 1:
        return f"{lead.method} (alone)"
    second = ranked[1]
    a, ah = getattr(lead, field), getattr(lead, f"{field}_band")
    b, bh = getattr(second, field), getattr(second, f"{field}_band")
    apart = "bands apart" if a - ah > b + bh else "bands overlap"
    ratio = f", x{a / b:.2f}" if b > 0 else ""
    return f"{lead.method} leads {second.method} by {a - b:.3g}{ratio} ({apart})"


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    p.add_argument("--budget", type=float, default=None,
                   help="designs scored at which methods are compared (default: the most that every method reached)")
    p.add_argument("--title", default=None, help="figure title (default: the runs' experiment name)")
    args = p.parse_args(argv)
    plt = common.pyplot()

    paths = common.find_runs(args.paths)
    runs = [load_run(r) for r in paths]
    methods = group(runs)
    budget = args.budget if args.budget is not None else min(float(np.nanmax(m.designs)) for m in methods)
    rows = [at_budget(m, budget) for m in methods]
    prov = common.provenance(paths)
    prov["budget_designs"] = f"{budget:g}"
    title = args.title or " | ".join(sorted({str(common.read_run_info(r).get("experiment")) for r in paths}))

    cols: dict[str, list[Any]] = {k: [] for k in ("method", "epoch", "designs", "mean", "mean_lower", "mean_upper",
                                                  "mean_raw", "best", "best_lower", "best_upper", "n_trials")}
    for m in methods:
        for i, e in enumerate(m.mean.epochs):
            for key, value in (("method", m.name), ("epoch", int(e)), ("designs", m.designs[i]),
                               ("mean", m.mean.mean[i]), ("mean_lower", m.mean.lower[i]),
                               ("mean_upper", m.mean.upper[i]), ("mean_raw", m.mean.raw_mean[i]),
                               ("best", m.best.mean[i]), ("best_lower", m.best.lower[i]),
                               ("best_upper", m.best.upper[i]), ("n_trials", int(m.mean.n_trials[i]))):
                cols[key].append(value)
    out = {"csv": common.write_csv(args.out / "rl_vs_evolution.csv", cols, prov)}
    out["summary_csv"] = common.write_csv(args.out / "rl_vs_evolution_summary.csv", {
        "method": [r.method for r in rows], "designs": [r.designs for r in rows],
        "population_mean": [r.mean for r in rows], "population_mean_band": [r.mean_band for r in rows],
        "best_so_far": [r.best for r in rows], "best_so_far_band": [r.best_band for r in rows],
        "wall_s_mean": [r.wall_s for r in rows], "seeds": [r.seeds for r in rows],
    }, prov)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for m in methods:
        variant = "+" in m.name  # ppo+dense(k): told apart from its base method by colour and dashes
        color = VARIANT_COLOR if variant else COLORS.get(m.name) or f"C{methods.index(m)}"
        style = "--" if variant else "-"
        for ax, curve in zip(axes, (m.mean, m.best), strict=True):
            ax.fill_between(m.designs, curve.lower, curve.upper, color=color, alpha=0.2, linewidth=0)
            ax.plot(m.designs, curve.mean, color=color, linestyle=style, linewidth=1.5,
                    label=f"{m.name} ({len(m.runs)} seeds)")
    for ax, what in zip(axes, ("population mean reward (±2-epoch average)", "best reward so far"), strict=True):
        ax.axvline(budget, color="0.6", linestyle=":", linewidth=1)
        ax.set_xlabel("designs scored (= simulated bodies on a physics task)")
        ax.set_ylabel(what)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{title}: mean and 99 % band over seeds", fontsize=10)
    fig.text(0.01, -0.03, common.provenance_caption(prov), fontsize=6, color="0.4")
    out.update(zip(("png", "pdf"), common.save_figure(fig, args.out, "rl_vs_evolution"), strict=True))

    print(f"{title}: {len(paths)} runs, compared at {budget:g} designs scored")
    print(f"{'method':<16}{'designs':>9}{'population mean':>22}{'best so far':>22}{'wall s':>9}  seeds")
    for r in rows:
        print(f"{r.method:<16}{r.designs:>9.0f}{r.mean:>14.2f} ± {r.mean_band:<5.2f}{r.best:>14.2f} ± "
              f"{r.best_band:<5.2f}{r.wall_s:>9.0f}  {r.seeds}")
    print(f"population mean: {verdict(rows, 'mean')}")
    print(f"best so far:     {verdict(rows, 'best')}")
    print("wrote " + ", ".join(str(v) for v in out.values()))
    return out


if __name__ == "__main__":
    common.run_cli(main)
