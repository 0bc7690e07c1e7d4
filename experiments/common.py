"""What every figure command shares: the paper's statistics, finding and reading runs, provenance, output.

Statistics (spec ppo.md, last section): per trial and epoch, the mean over that epoch's episodes; across trials,
the mean and a 99 % normal confidence band ``mean ± 2.576·sd/√n`` (sd with Bessel's correction, n = number of
trials); curves smoothed with a ±2-epoch centred moving average (windows shrink at the ends).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freeform.tables import (  # noqa: F401 (the figure commands import them from here too)
    Z_99,
    mean_band,
    missing_figure,
    paired_band,
    read_rows,
    summary_row,
    write_rows,
)

SMOOTH_HALF_WINDOW = 2
"""The paper's ±2-epoch moving average."""

RUN_INFO = "run_info.json"


# ---------------------------------------------------------------------------------------------------- statistics
def moving_average(x: np.ndarray, half_window: int = SMOOTH_HALF_WINDOW) -> np.ndarray:
    """Centred moving average over the last axis: ``y[i] = mean(x[i-w : i+w+1])``, the window cut at the ends.

    ``x``: ``[..., E]``. ``half_window`` = 0 returns a copy. NaNs are skipped inside a window.
    """
    if half_window < 0:
        raise ValueError(f"half_window must be >= 0, got {half_window}")
    x = np.asarray(x, dtype=np.float64)
    if half_window == 0 or x.shape[-1] == 0:
        return x.copy()
    finite = np.isfinite(x)
    filled = np.where(finite, x, 0.0)
    # Cumulative sums give every window's sum and count in O(E), with no Python loop over epochs.
    pad = [(0, 0)] * (x.ndim - 1) + [(1, 0)]
    csum = np.pad(np.cumsum(filled, axis=-1), pad)
    ccnt = np.pad(np.cumsum(finite, axis=-1), pad)
    e = x.shape[-1]
    lo = np.clip(np.arange(e) - half_window, 0, e)
    hi = np.clip(np.arange(e) + half_window + 1, 0, e)
    s = csum[..., hi] - csum[..., lo]
    c = ccnt[..., hi] - ccnt[..., lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(c > 0, s / np.maximum(c, 1), np.nan)


@dataclass
class Curve:
    """An across-trial curve: per-epoch mean and 99 % band, smoothed as the paper does."""

    epochs: np.ndarray  # [E] int
    mean: np.ndarray  # [E] smoothed mean across trials
    lower: np.ndarray  # [E] mean - half-width (both smoothed)
    upper: np.ndarray  # [E]
    raw_mean: np.ndarray  # [E] unsmoothed mean across trials
    n_trials: np.ndarray  # [E] int, trials that reached this epoch


def across_trials(per_trial: np.ndarray, epochs: np.ndarray | None = None,
                  half_window: int = SMOOTH_HALF_WINDOW) -> Curve:
    """``per_trial``: ``[n_trials, E]`` (NaN where a trial has no such epoch) -> the smoothed curve and band.

    The band's half-width is smoothed with the same window as the mean, so the band stays centred on the curve.
    """
    per_trial = np.atleast_2d(np.asarray(per_trial, dtype=np.float64))
    mean, half = mean_band(per_trial, axis=0)
    m = moving_average(mean, half_window)
    h = moving_average(half, half_window)
    e = per_trial.shape[1]
    return Curve(
        epochs=np.arange(e) if epochs is None else np.asarray(epochs),
        mean=m, lower=m - h, upper=m + h, raw_mean=mean,
        n_trials=np.sum(np.isfinite(per_trial), axis=0),
    )


# ---------------------------------------------------------------------------------------------------- runs
def find_runs(paths: Iterable[str | Path]) -> list[Path]:
    """Run directories under ``paths``: each path that holds ``run_info.json`` is a run; any other directory (a
    Hydra multirun sweep) is searched recursively. Sorted, without duplicates.
    """
    paths = [Path(p) for p in paths]
    found: list[Path] = []
    for p in paths:
        if not p.exists():
            raise ValueError(f"paths: {p} does not exist")
        if (p / RUN_INFO).is_file():
            found.append(p.resolve())
        else:  # follow symbolic links: a sweep may be assembled from links to runs made elsewhere
            found.extend(sorted(Path(d).resolve() for d, _, files in os.walk(p, followlinks=True) if RUN_INFO in files))
    runs = sorted(dict.fromkeys(found))
    if not runs:
        raise ValueError(f"paths: no run directory (one holding {RUN_INFO}) under {[str(p) for p in paths]}")
    return runs


def read_run_info(run: Path) -> dict[str, Any]:
    """The run's ``run_info.json`` (versions, device, git commit, seed, ...)."""
    with open(Path(run) / RUN_INFO) as f:
        return json.load(f)


PROVENANCE_KEYS = ("freeform", "torch", "taichi", "sim_backend", "device", "git_commit")
# sim_backend: what ran the simulator's kernels, "taichi 1.7.4" | "quadrants 1.3.3" (run_info.json names it since
# there are two); a run from before that ran on Taichi, whose version it records.
PRE_BACKEND_DEFAULT = "taichi"


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def provenance(runs: Sequence[Path]) -> dict[str, str]:
    """What made the runs: each of :data:`PROVENANCE_KEYS` as found in the runs' ``run_info.json`` (a key is matched
    by its last dotted component, so ``versions.torch`` counts as ``torch``); differing values are joined by " | "
    and a missing key reads "unknown".
    """
    values: dict[str, list[str]] = {k: [] for k in PROVENANCE_KEYS}
    for run in runs:
        flat = _flatten(read_run_info(run))
        if flat.get("device_name") and "device" in flat:  # e.g. "cuda (NVIDIA A100-SXM4-80GB)"
            flat["device"] = f"{flat['device']} ({flat['device_name']})"
        last = {k.split(".")[-1]: v for k, v in flat.items()}
        if "sim_backend" not in last and last.get("taichi"):  # a run from before the backend switch
            flat["sim_backend"] = f"{PRE_BACKEND_DEFAULT} {last['taichi']}"
        if flat.get("git_dirty") and flat.get("git_commit"):  # uncommitted changes made this run
            flat["git_commit"] = f"{flat['git_commit']}+dirty"
        for key in PROVENANCE_KEYS:
            hits = [str(v) for k, v in flat.items() if k.split(".")[-1] in _ALIASES[key]]
            if hits and hits[0] not in values[key]:
                values[key].append(hits[0])
    out = {k: (" | ".join(v) if v else "unknown") for k, v in values.items()}
    out["runs"] = str(len(runs))
    return out


_ALIASES = {
    "freeform": ("freeform", "freeform_version"),
    "torch": ("torch", "torch_version"),
    "taichi": ("taichi", "taichi_version"),
    "sim_backend": ("sim_backend",),
    "device": ("device",),
    "git_commit": ("git_commit", "commit", "git", "git_sha"),
}


def provenance_caption(prov: dict[str, str]) -> str:
    """One line naming what made a figure."""
    return (f"{prov['runs']} run(s); freeform {prov['freeform']}, torch {prov['torch']}, sim {prov['sim_backend']}, "
            f"device {prov['device']}, commit {prov['git_commit'][:12]}")


# ---------------------------------------------------------------------------------------------------- output
def write_csv(path: Path, columns: dict[str, Sequence[Any]], prov: dict[str, str] | None = None) -> Path:
    """Write equal-length ``columns`` as CSV, preceded by ``# key: value`` provenance comment lines."""
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise ValueError(f"columns: lengths differ: { {k: len(v) for k, v in columns.items()} }")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        for k, v in (prov or {}).items():
            f.write(f"# {k}: {v}\n")
        w = csv.writer(f)
        w.writerow(columns.keys())
        for row in zip(*columns.values(), strict=True):
            w.writerow([_fmt(x) for x in row])
    return path


def read_csv(path: Path) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    """Inverse of :func:`write_csv`: ``(provenance, columns)``; numeric columns come back as float arrays."""
    prov: dict[str, str] = {}
    lines = []
    with open(path) as f:
        for line in f:
            if line.startswith("# "):
                k, _, v = line[2:].rstrip("\n").partition(": ")
                prov[k] = v
            else:
                lines.append(line)
    rows = list(csv.reader(lines))
    header, body = rows[0], rows[1:]
    cols: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        col = [r[i] for r in body]
        try:
            cols[name] = np.array([float(x) for x in col])
        except ValueError:
            cols[name] = np.array(col)
    return prov, cols


def _fmt(x: Any) -> Any:
    if isinstance(x, float | np.floating):
        return f"{float(x):.6g}"
    return x


def save_figure(fig: Any, out: Path, name: str) -> list[Path]:
    """Save ``fig`` as ``out/name.png`` and ``out/name.pdf``; close it."""
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{name}.png", out / f"{name}.pdf"]
    for p in paths:
        fig.savefig(p, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return paths


def pyplot() -> Any:
    """matplotlib.pyplot on the non-interactive Agg backend, or a clear error naming the extra to install."""
    try:
        import matplotlib
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise SystemExit("the figure commands need matplotlib: pip install 'freeform[experiments]'") from e
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curve(ax: Any, curve: Curve, label: str | None = None, color: str = "0.25",
               band_color: str | None = None) -> None:
    """The paper's style: dark mean curve over a light 99 % band."""
    ax.fill_between(curve.epochs, curve.lower, curve.upper, color=band_color or color, alpha=0.25, linewidth=0)
    ax.plot(curve.epochs, curve.mean, color=color, linewidth=1.5, label=label)


def run_cli(main: Any) -> None:
    """Run a figure command's ``main()``; a ``ValueError`` (bad paths, missing records...) becomes a one-line
    error message and exit status 1 instead of a traceback."""
    try:
        main()
    except ValueError as exc:
        name = Path(sys.argv[0]).stem
        raise SystemExit(f"experiments.{name}: error: {exc}") from exc


def base_parser(description: str) -> argparse.ArgumentParser:
    """The arguments every figure command takes: run directories (or sweep directories) and ``--out``."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("paths", nargs="+", help="sweep directories (searched for runs) or run directories")
    p.add_argument("--out", required=True, type=Path, help="directory for the figure (PNG, PDF) and its CSV")
    return p


def add_overrides(p: argparse.ArgumentParser, use: str) -> None:
    """``--set KEY=VALUE ...`` (``args.overrides``): dotted keys of each run's config, merged and validated by
    ``experiments.robustness.run_train_config``; ``use`` says what the command does with them."""
    p.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", dest="overrides",
                   help=f"dotted overrides of each run's config {use}, e.g. sim.burn_in=2.0")


# ---------------------------------------------------------------------------------------------------- trials
@dataclass
class Trial:
    """One run's per-epoch summary, read from its design records (``freeform.records``).

    epochs: ``[E]`` int, the recorded epochs in order. reward: ``[E]`` mean episode reward of each epoch.
    reward_max: ``[E]`` the epoch's best episode reward (−inf for an epoch without episodes).
    metrics: ``{name: [E]}`` mean of each recorded body metric. episodes: ``[E]`` episodes per epoch.
    """

    path: Path
    info: dict[str, Any]
    epochs: np.ndarray
    reward: np.ndarray
    reward_max: np.ndarray
    metrics: dict[str, np.ndarray]
    episodes: np.ndarray

    @property
    def seed(self) -> Any:
        return self.info.get("seed", self.path.name)


def load_trial(run: Path) -> Trial:
    """Read every design record of ``run`` into per-epoch means (``ValueError`` if it has none)."""
    from freeform.records import iter_records

    epochs, reward, reward_max, episodes = [], [], [], []
    metrics: dict[str, list[float]] = {}
    for rec in iter_records(run):
        epochs.append(rec.epoch)
        reward.append(float(np.mean(rec.rewards)) if rec.num_episodes else np.nan)
        reward_max.append(float(np.max(rec.rewards)) if rec.num_episodes else -np.inf)
        episodes.append(rec.num_episodes)
        for name, m in rec.metrics.items():
            metrics.setdefault(name, []).append(float(np.mean(m)) if len(m) else np.nan)
    if not epochs:
        raise ValueError(f"paths: run {run} has no design records (records/epoch_*.npz; trainer.record_designs=true)")
    return Trial(path=Path(run), info=read_run_info(run), epochs=np.asarray(epochs), reward=np.asarray(reward),
                 reward_max=np.asarray(reward_max),
                 metrics={k: np.asarray(v) for k, v in metrics.items()}, episodes=np.asarray(episodes))


def align(trials: Sequence[Trial], values: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Put each trial's per-epoch ``values`` on the union of their epochs: ``(epochs [E], [n_trials, E])``, NaN
    where a trial lacks an epoch (runs of different length, or a resumed run with a gap)."""
    all_epochs = np.unique(np.concatenate([t.epochs for t in trials]))
    out = np.full((len(trials), len(all_epochs)), np.nan)
    for i, (t, v) in enumerate(zip(trials, values, strict=True)):
        out[i, np.searchsorted(all_epochs, t.epochs)] = v
    return all_epochs, out


def run_config(run: Path) -> dict[str, Any]:
    """The run's resolved training config as a nested dict (``freeform.config.to_container`` form).

    Read from the run's last checkpoint (what the run actually used), else from Hydra's ``.hydra/config.yaml``.
    """
    from freeform.checkpoint import CHECKPOINT_DIR, LAST, CheckpointError, load_checkpoint

    run = Path(run)
    candidates = [run / CHECKPOINT_DIR / LAST, *sorted((run / CHECKPOINT_DIR).glob("epoch_*.pt"))]
    for path in candidates:
        if path.is_file():
            try:
                return dict(load_checkpoint(path)["config"])
            except (CheckpointError, KeyError):
                continue
    hydra_cfg = run / ".hydra" / "config.yaml"
    if hydra_cfg.is_file():
        from omegaconf import OmegaConf

        from freeform.config import to_container, to_dataclass

        return to_container(to_dataclass(OmegaConf.load(hydra_cfg)))
    raise ValueError(f"paths: run {run} has neither a checkpoint nor .hydra/config.yaml to read its config from")


# ---------------------------------------------------------------------------------------------------- bodies
def body_of(grid: np.ndarray) -> np.ndarray:
    """The robot body of one final grid (``[ρ, ρ, ρ] uint8``): its largest 6-connected component, same shape."""
    import torch

    from freeform.body import largest_component

    return largest_component(torch.as_tensor(np.asarray(grid, dtype=np.uint8))[None])[0].numpy()


def draw_body(ax: Any, grid: np.ndarray, body: np.ndarray | None = None, title: str | None = None,
              size: int = 320) -> None:
    """Draw a final grid (``[ρ, ρ, ρ] uint8``, z up) on a 2-D matplotlib axis with ``freeform.render``: the body
    in the paper's colours, the rest of the grid translucent grey, in the ρ³ design space."""
    from freeform.render import RenderConfig, render_grid

    ax.imshow(render_grid(grid, body, RenderConfig(size=size)))
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=8)
