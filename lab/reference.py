"""The reference's own convergence curve: a bank of per-body controllers (a teacher run, e.g. ``--per-body``'s cache
in ``runs/per_body/``) played on its bodies at every epoch it saved — each body by its own controller's mean command,
all bodies in one env, one row each.

    python -m lab.reference runs/per_body/control_teachers_cpu_32_<key> --out lab/results/reference/design_unseen32

Writes ``curve.csv`` (per saved epoch: the bodies' mean move and its 99 % band, the training return of that epoch,
and whether the run's own rule had called it flat there: ``trainer.plateau_window`` on ``plateau_on``'s curve),
``bodies.csv`` (per body, its move at each saved epoch) and ``curve.png``. A fraction of per-body control is only as
honest as this curve is flat at its end.

Along random headings (steering) a body's move is the mean over ``--episodes`` episodes (default ``evaluate``'s 4:
episodes 0 … 3 of each body, what ``freeform-control evaluate`` and ``fit`` measure a body on); other tasks play one.

How far from flat: ``asymptote.csv`` extrapolates the mean curve by a saturating exponential, a − b·exp(−t/τ) (least
squares; τ on a fine geometric grid), and gives a with a 99 % interval from resampling the bodies, τ, and the share of
a the last saved epoch reached. A curve that has not bent within its span (τ longer than it), or has fewer than four
saved epochs, gives no asymptote (NaN). The interval is the bodies' spread under that one model, not the model's
error: a check on the plateau, not a reference.
"""

from __future__ import annotations

import argparse
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from freeform.tables import mean_band, write_rows

PLATEAU = (20, 0.02)
"""The flatness read where the run set none (``trainer.plateau_window``, ``plateau_gain``): the last 20 epochs' mean
return adds < 2 % over the 20 before."""


def saved_epochs(run: Path) -> list[tuple[int, Path]]:
    """The run's numbered checkpoints ``(epoch, path)`` in order, and ``last.pt`` where it is later than them."""
    from freeform.checkpoint import CHECKPOINT_DIR, LAST, load_checkpoint, numbered_name

    folder = run / CHECKPOINT_DIR
    numbered = sorted((e, p) for p in folder.glob("*.pt")
                      if (m := re.search(r"\d+", p.name)) and p.name == numbered_name(e := int(m.group())))
    last = folder / LAST
    if last.is_file():
        epoch = int(load_checkpoint(last)["epoch"])
        if not numbered or epoch > numbered[-1][0]:
            numbered.append((epoch, last))
    if not numbered:
        raise ValueError(f"{run}: no checkpoints in {folder}: give a teacher run's directory")
    return numbered


@torch.no_grad()
def curve(run: Path, episodes: int | None = None) -> tuple[list[dict], list[dict]]:
    """The bank of ``run`` at each saved epoch on its bodies, each body's move the mean over ``episodes`` (None: the
    module's default; more than one only along random headings): (a row per epoch, a row per body)."""
    from freeform.agents.controller_file import body_box
    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import load_checkpoint
    from freeform.control.evaluate import episode_draws, figure_episodes
    from freeform.control.play import own_moves
    from freeform.envs.control import ControlEnv
    from freeform.run.build import read_teacher_run
    from freeform.run.trainer import flattened

    teachers = read_teacher_run(run, str(run))
    grids, cfg = teachers.bodies.to(torch.uint8), teachers.config
    m, box, control = len(grids), body_box(teachers.bodies), cfg.control.episode()
    k = figure_episodes(control.headings, episodes, who=f"the run {run}")
    returns, evaluated = teachers.payload.get("return_curve", []), teachers.payload.get("eval_curve", [])
    rule = cfg if cfg.trainer.plateau_window else replace(cfg, trainer=replace(
        cfg.trainer, plateau_window=PLATEAU[0], plateau_gain=PLATEAU[1], plateau_on="return"))
    per_epoch, per_body = [], [{"body": i} for i in range(m)]
    for epoch, path in saved_epochs(run):
        bank = bank_from_checkpoint(load_checkpoint(path), str(path))
        env = ControlEnv(grids.repeat_interleave(k, 0), sim=cfg.sim, control=control, seed=0, box=box,
                         first_env=episode_draws(m, k))  # (a fresh env each epoch: one more episode draws anew)
        moved = own_moves(bank, env, episodes=k).reshape(m, k).mean(1)
        mean, band = mean_band(moved)
        per_epoch.append({"epoch": epoch, "episodes": k, "mean_command": float(mean), "band99": float(band),
                          "training_return": returns[epoch - 1] if 0 < epoch <= len(returns) else float("nan"),
                          "flat": flattened(rule, returns, evaluated, epoch)})
        for i in range(m):
            per_body[i][f"epoch{epoch}"] = float(moved[i])
        print(f"epoch {epoch}: {mean:.3f} ± {band:.3f}", flush=True)
    return per_epoch, per_body


TAUS = np.geomspace(1.0, 5000.0, 600)
"""The time constants (epochs) the saturating fit tries."""
MIN_EPOCHS = 4
"""The fewest saved epochs the fit reads: three parameters through three points leave it no residual."""


def saturating_fit(t: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """(a, b, τ) of y ≈ a − b·exp(−(t − t₀)/τ), t₀ the first epoch, by least squares over :data:`TAUS` (a and b are
    linear for each τ). a is NaN where the curve has not bent within its span — the best τ longer than it: less than
    63 % of the rise seen, so that a would extrapolate further than the part observed — or where it has fewer than
    :data:`MIN_EPOCHS` points."""
    if len(t) < MIN_EPOCHS:
        return float("nan"), float("nan"), float("nan")
    span = t - t[0]  # (from the first epoch: exp(−t/τ) of a late start would underflow)
    e = np.exp(-span[None, :] / TAUS[:, None])  # [τ, t]
    de, dy = e - e.mean(1, keepdims=True), y - y.mean()
    b = -(de @ dy) / (de * de).sum(1)  # (the regression of y on −e, each τ)
    a = y.mean() + b * e.mean(1)
    k = int(np.nanargmin((((a[:, None] - b[:, None] * e) - y) ** 2).sum(1)))
    return (float(a[k]) if TAUS[k] <= span[-1] else float("nan")), float(b[k]), float(TAUS[k])


def asymptote(epochs: np.ndarray, moves: np.ndarray, resamples: int = 400, seed: int = 0) -> dict:
    """The mean curve's saturating fit (module docstring) for ``moves`` ``[bodies, epochs]``: the asymptote a, its 99 %
    interval over resampled bodies (a resample whose curve has not bent counts as unbounded: the upper end is then
    inf), b and τ, and the last epoch's share of a. Without an asymptote the interval is NaN too."""
    t = np.asarray(epochs, dtype=float)
    a, b, tau = saturating_fit(t, moves.mean(0))
    rng = np.random.default_rng(seed)
    again = np.array([saturating_fit(t, moves[rng.integers(0, len(moves), len(moves))].mean(0))[0]
                      for _ in range(resamples)])
    low, high = (np.percentile(np.where(np.isnan(again), np.inf, again), [0.5, 99.5], method="nearest")
                 if np.isfinite(a) else (a, a))  # ("nearest": an unbounded resample gives inf, not inf − inf)
    return {"asymptote": a, "low99": float(low), "high99": float(high), "b": b, "tau_epochs": tau,
            "first_epoch": int(t[0]), "last_epoch": int(t[-1]), "reached": float(moves.mean(0)[-1] / a),
            "unbent_resamples": int(np.isnan(again).sum())}


def plot(rows: list[dict], path: Path, fit: dict | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    e = [r["epoch"] for r in rows]
    mean, band = np.array([r["mean_command"] for r in rows]), np.array([r["band99"] for r in rows])
    ax.plot(e, mean, "o-", label="per-body controllers, mean command")
    ax.fill_between(e, mean - band, mean + band, alpha=0.2)
    if fit is not None and np.isfinite(fit["asymptote"]):  # (the fit drawn on, its interval in the legend only)
        t = np.linspace(fit["first_epoch"], 2 * fit["last_epoch"], 200)
        a, b, tau = fit["asymptote"], fit["b"], fit["tau_epochs"]
        ax.plot(t, a - b * np.exp(-(t - fit["first_epoch"]) / tau), "--", color="grey",
                label=f"a − b·exp(−t/{tau:.0f}): a = {a:.2f} (99 %: {fit['low99']:.2f} – {fit['high99']:.2f})")
    ax.set_xlabel("epochs of per-body training")
    ax.set_ylabel("move in 2 s (voxel lengths)")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="a teacher run (a per-body cache's directory)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--episodes", type=int, default=None,
                   help="steering: episodes a body's move averages (default evaluate's, 4)")
    args = p.parse_args(argv)
    if (args.out / "curve.csv").exists():
        p.error(f"--out {args.out} holds a curve already (curve.csv): give a new folder (nothing is overwritten)")
    try:
        rows, bodies = curve(args.run, args.episodes)
    except ValueError as e:
        p.error(str(e))
    epochs = np.array([r["epoch"] for r in rows])
    fit = asymptote(epochs, np.array([[b[f"epoch{e}"] for e in epochs] for b in bodies]))
    args.out.mkdir(parents=True, exist_ok=True)
    write_rows(args.out / "curve.csv", rows)
    write_rows(args.out / "bodies.csv", bodies)
    write_rows(args.out / "asymptote.csv", [fit])
    print(f"asymptote {fit['asymptote']:.3f} (99 %: {fit['low99']:.3f} – {fit['high99']:.3f}), τ {fit['tau_epochs']:.0f} "
          f"epochs; epoch {fit['last_epoch']} reached {fit['reached']:.1%} of it")
    plot(rows, args.out / "curve.png", fit)


if __name__ == "__main__":
    main()
