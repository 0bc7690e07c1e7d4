"""Paper Fig. 4 A-H — learning to design robots: reward and the seven body metrics across trials.

    python -m experiments.locomotion runs/paper_locomotion/<sweep> --out figures/locomotion

Reads each run's design records (rewards and the body metrics ``freeform.body.metrics`` recorded per episode).
Per trial and epoch the mean over the epoch's episodes; across trials the mean and its 99 % normal band, both
smoothed with a ±2-epoch moving average. Writes ``locomotion.png``/``.pdf`` (eight panels, A = reward ... H =
compressibility) and ``locomotion_metrics.csv`` (per epoch: ``<panel>_mean``, ``_lower``, ``_upper``,
``_raw_mean`` for each panel, and ``n_trials``). Works for any task's runs (the volume runs too).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from experiments import common

PANELS: tuple[tuple[str, str], ...] = (
    ("reward", "reward (displacement, voxel lengths)"),
    ("volume", "body volume (voxels)"),
    ("surface_ratio", "surface voxels / volume"),
    ("passive_ratio", "passive material ratio"),
    ("lcc_ratio", "largest component ratio"),
    ("substructures", "substructures"),
    ("symmetry", "reflection symmetry"),
    ("compressibility", "compressibility (gzip ratio)"),
)
"""The paper's Fig. 4 panels in order (A-H): record key and axis label."""


def panel_curves(trials: Sequence[common.Trial], half_window: int = common.SMOOTH_HALF_WINDOW
                 ) -> tuple[np.ndarray, dict[str, common.Curve]]:
    """``(epochs [E], {panel: Curve})`` for the panels every trial recorded (reward always)."""
    curves: dict[str, common.Curve] = {}
    epochs = None
    for key, _ in PANELS:
        if key != "reward" and not all(key in t.metrics for t in trials):
            continue
        values = [t.reward if key == "reward" else t.metrics[key] for t in trials]
        epochs, per_trial = common.align(trials, values)
        curves[key] = common.across_trials(per_trial, epochs, half_window)
    assert epochs is not None
    return epochs, curves


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    p.add_argument("--smooth", type=int, default=common.SMOOTH_HALF_WINDOW,
                   help="half-width of the moving average in epochs (paper: 2)")
    args = p.parse_args(argv)
    plt = common.pyplot()

    runs = common.find_runs(args.paths)
    trials = [common.load_trial(r) for r in runs]
    epochs, curves = panel_curves(trials, args.smooth)
    missing = [k for k, _ in PANELS if k not in curves]
    prov = common.provenance(runs)

    cols: dict[str, Sequence] = {"epoch": epochs, "n_trials": curves["reward"].n_trials}
    for key, c in curves.items():
        cols.update({f"{key}_mean": c.mean, f"{key}_lower": c.lower, f"{key}_upper": c.upper,
                     f"{key}_raw_mean": c.raw_mean})
    out = {"csv": common.write_csv(args.out / "locomotion_metrics.csv", cols, prov)}

    fig, axes = plt.subplots(2, 4, figsize=(14, 6), sharex=True)
    for i, (ax, (key, label)) in enumerate(zip(axes.flat, PANELS, strict=True)):
        ax.set_title(f"{chr(ord('A') + i)}  {label}", fontsize=9, loc="left")
        if key in curves:
            common.plot_curve(ax, curves[key])
        else:
            ax.text(0.5, 0.5, "not recorded", ha="center", va="center", transform=ax.transAxes, color="0.5")
        if i >= 4:
            ax.set_xlabel("epoch")
    fig.suptitle(f"Learning to design robots: mean and 99 % band across {len(runs)} trial(s)", fontsize=11)
    fig.text(0.01, -0.01, common.provenance_caption(prov), fontsize=6, color="0.4")
    fig.tight_layout()
    out.update(zip(("png", "pdf"), common.save_figure(fig, args.out, "locomotion"), strict=True))

    first = 0
    last = int(np.flatnonzero(np.isfinite(curves["reward"].raw_mean))[-1])
    print(f"locomotion: {len(runs)} trial(s), epochs {int(epochs[0])}..{int(epochs[-1])}")
    for key, c in curves.items():
        print(f"  {key:16s} first {c.raw_mean[first]:9.4f}  last {c.raw_mean[last]:9.4f}")
    if missing:
        print(f"  not recorded by every run: {missing}")
    print("wrote " + ", ".join(str(v) for v in out.values()))
    return out


if __name__ == "__main__":
    common.run_cli(main)
