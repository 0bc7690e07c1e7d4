"""Paper Fig. 2 — learning to design large bodies: mean volume reward across trials, and six example bodies.

    python -m experiments.volume runs/paper_volume/<sweep> --out figures/volume

Reads each run's design records. Writes ``volume.png``/``volume.pdf`` (left: the mean reward with its 99 % band
across trials, smoothed ±2 epochs; right: bodies A-F), ``volume_reward.csv`` (the curve, plus the across-trial
mean of every recorded body metric, e.g. the largest-component ratio the paper quotes: 11.62 % untrained, 82.62 %
trained) and ``volume_bodies.csv`` (which episode each body is). The bodies are drawn at the epoch fractions
0, .1, .2, .4, .6, 1 of training; each is the body, among all trials' episodes of that epoch, whose reward is
closest to the epoch's mean reward (spec ppo.md, last section).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from experiments import common

BODY_FRACTIONS = (0.0, 0.1, 0.2, 0.4, 0.6, 1.0)
"""Where along training the paper's six example bodies are taken (fractions of the epochs)."""


@dataclass
class ExampleBody:
    label: str
    epoch: int
    trial: int  # index into the runs
    episode: int
    reward: float
    target: float  # the epoch's mean reward the body is closest to
    grid: np.ndarray  # [ρ, ρ, ρ] uint8, the final grid
    body: np.ndarray  # [ρ, ρ, ρ] uint8, its largest component


def example_bodies(trials: Sequence[common.Trial], curve: common.Curve,
                   fractions: Sequence[float] = BODY_FRACTIONS) -> list[ExampleBody]:
    """The episode closest to the mean reward at each epoch fraction (epochs that every trial reached)."""
    from freeform.records import read_record, record_path

    if any(not 0 <= f <= 1 for f in fractions):
        raise ValueError(f"fractions must lie in [0, 1], got {list(fractions)}")
    complete = curve.epochs[curve.n_trials == len(trials)]
    eligible = complete if len(complete) else curve.epochs
    out = []
    for i, f in enumerate(fractions):
        epoch = int(eligible[int(round(f * (len(eligible) - 1)))])
        target = float(curve.raw_mean[np.searchsorted(curve.epochs, epoch)])
        best: tuple[float, int, int, float, np.ndarray] | None = None
        for ti, t in enumerate(trials):
            if epoch not in t.epochs:
                continue
            rec = read_record(record_path(t.path, epoch))
            if rec.num_episodes == 0:
                continue
            j = int(np.argmin(np.abs(rec.rewards - target)))  # first of equals: deterministic
            gap = abs(float(rec.rewards[j]) - target)
            if best is None or gap < best[0]:
                best = (gap, ti, j, float(rec.rewards[j]), rec.final_grids[j])
        if best is None:
            continue
        _, ti, j, reward, grid = best
        out.append(ExampleBody(label=chr(ord("A") + i), epoch=epoch, trial=ti, episode=j, reward=reward,
                               target=target, grid=grid, body=common.body_of(grid)))
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    p.add_argument("--fractions", type=float, nargs="+", default=list(BODY_FRACTIONS),
                   help="epoch fractions of the example bodies (default: the paper's 0 .1 .2 .4 .6 1)")
    args = p.parse_args(argv)
    plt = common.pyplot()

    runs = common.find_runs(args.paths)
    trials = [common.load_trial(r) for r in runs]
    epochs, per_trial = common.align(trials, [t.reward for t in trials])
    curve = common.across_trials(per_trial, epochs)
    metric_names = sorted(set.intersection(*(set(t.metrics) for t in trials)))
    metric_curves = {m: common.across_trials(common.align(trials, [t.metrics[m] for t in trials])[1], epochs)
                     for m in metric_names}
    bodies = example_bodies(trials, curve, args.fractions)
    prov = common.provenance(runs)

    cols: dict[str, Sequence] = {"epoch": curve.epochs, "reward_mean": curve.mean, "reward_lower": curve.lower,
                                 "reward_upper": curve.upper, "reward_raw_mean": curve.raw_mean,
                                 "n_trials": curve.n_trials}
    for m, c in metric_curves.items():
        cols[f"{m}_raw_mean"] = c.raw_mean
    out: dict[str, Path] = {"reward_csv": common.write_csv(args.out / "volume_reward.csv", cols, prov)}
    out["bodies_csv"] = common.write_csv(args.out / "volume_bodies.csv", {
        "label": [b.label for b in bodies], "epoch": [b.epoch for b in bodies],
        "run": [str(runs[b.trial]) for b in bodies], "episode": [b.episode for b in bodies],
        "reward": [b.reward for b in bodies], "epoch_mean_reward": [b.target for b in bodies],
    }, prov)

    fig = plt.figure(figsize=(12, 4.2))
    grid = fig.add_gridspec(2, 5, width_ratios=[1.3, 1.3, 1, 1, 1])
    ax = fig.add_subplot(grid[:, :2])
    common.plot_curve(ax, curve)
    for b in bodies:
        ax.annotate(b.label, (b.epoch, b.target), textcoords="offset points", xytext=(0, 8), ha="center",
                    fontsize=9, fontweight="bold")
        ax.plot([b.epoch], [b.target], "o", color="k", markersize=3)
    ax.set_xlabel("epoch")
    ax.set_ylabel("reward (body volume, voxels)")
    ax.set_title(f"volume, {len(runs)} trial(s), mean and 99 % band")
    for i, b in enumerate(bodies):
        bax = fig.add_subplot(grid[i // 3, 2 + i % 3])
        common.draw_body(bax, b.grid, b.body, f"{b.label}: epoch {b.epoch}, volume {b.reward:.0f}")
    fig.text(0.01, -0.02, common.provenance_caption(prov), fontsize=6, color="0.4")
    out.update(zip(("png", "pdf"), common.save_figure(fig, args.out, "volume"), strict=True))

    last = np.flatnonzero(np.isfinite(curve.raw_mean))[-1]
    print(f"volume: {len(runs)} trial(s), epochs {int(curve.epochs[0])}..{int(curve.epochs[-1])}, "
          f"mean reward first {curve.raw_mean[0]:.1f} -> last {curve.raw_mean[last]:.1f}")
    for m, c in metric_curves.items():
        if "component" in m or "lcc" in m:
            print(f"  {m}: first {c.raw_mean[0]:.4f} -> last {c.raw_mean[last]:.4f} (paper: 0.1162 -> 0.8262)")
    print("wrote " + ", ".join(str(v) for v in out.values()))
    return out


if __name__ == "__main__":
    common.run_cli(main)
