"""Paper Fig. 6 — robustness: the reward of designs cut short after t = 1 … T design actions.

    python -m experiments.robustness runs/paper_locomotion/<sweep> --out figures/robustness

As the authors computed it (spec ppo.md, last section): the recorded raw actions of every episode of a late epoch
(default: each trial's last recorded epoch) are replayed step by step through the design rule (``DesignEnv``; no
policy), and after each step t the partial design is scored by the run's own task — for locomotion its largest
component is simulated with the run's protocol. The mean reward against t, over trials × robots, with its 99 %
band. The replay is checked against the recorded final grids (it must reproduce them exactly). Writes
``robustness.png``/``.pdf`` and ``robustness.csv`` (per t: mean, band, n, and each trial's mean).

``--set sim.duration=1.0`` (dotted keys of the run's config) changes the scoring protocol, e.g. for a cheaper look.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments import common


def run_train_config(run: Path, overrides: Sequence[str] = ()) -> Any:
    """The run's ``freeform.config.TrainConfig``, with dotted ``key=value`` overrides merged in (validated)."""
    from omegaconf import OmegaConf

    from freeform.config import to_dataclass

    cfg = OmegaConf.create(common.run_config(run))
    if overrides:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    return to_dataclass(cfg)


def replay(cfg: Any, actions: np.ndarray, device: torch.device) -> torch.Tensor:
    """Partial designs after each action: ``actions [E, T, A]`` -> uint8 ``[T, E, ρ, ρ, ρ]`` (index t-1 = after t
    actions), through the run's design rule (``DesignEnv.place_bundles``)."""
    from freeform.envs import DesignEnv, EnvConfig

    e, steps, _ = actions.shape
    design = EnvConfig(resolution=cfg.env.resolution, steps=steps, bundle_size=cfg.env.bundle_size,
                       action_bound=getattr(cfg.env, "action_bound", 2.0), mirror_y=getattr(cfg.env, "mirror_y", False))
    env = DesignEnv(e, design, materials=cfg.task.materials, device=device, compute_metrics=False)
    grids = env.reset()
    acts = torch.as_tensor(actions, dtype=torch.float32, device=device)
    out = []
    for t in range(steps):  # T sequential design steps; each is one vectorised operation over all robots
        grids = env.place_bundles(grids, acts[:, t])
        out.append(grids)
    return torch.stack(out)


def score(task: Any, designs: torch.Tensor, batch_size: int) -> np.ndarray:
    """Task reward of every design ``[M, ρ, ρ, ρ]`` in batches of ``batch_size`` -> ``[M] float64``."""
    parts = [task.reward(designs[i:i + batch_size]).double().cpu() for i in range(0, len(designs), batch_size)]
    return torch.cat(parts).numpy()


def robustness(run: Path, epoch: int | None, steps: Sequence[int] | None, device: torch.device, batch_size: int,
               overrides: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """``(t [S], rewards [S, E], meta)`` for one trial: the reward after t actions of each of the epoch's robots."""
    from freeform.records import list_records, read_record, record_path
    from freeform.train import build_task

    files = list_records(run)
    if not files:
        raise ValueError(f"paths: run {run} has no design records")
    path = files[-1] if epoch is None else record_path(run, epoch)
    if not path.is_file():
        raise ValueError(f"--epoch: run {run} has no record of epoch {epoch}")
    rec = read_record(path)
    cfg = run_train_config(run, overrides)
    designs = replay(cfg, rec.actions, device)  # [T, E, ρ, ρ, ρ]
    recorded = torch.as_tensor(rec.final_grids, device=device)
    if not torch.equal(designs[-1], recorded):
        bad = int((designs[-1] != recorded).flatten(1).any(1).sum())
        raise ValueError(f"run {run}, epoch {rec.epoch}: replaying the recorded actions does not reproduce "
                         f"{bad} of {rec.num_episodes} recorded final grids (design rule or config changed?)")
    total = designs.shape[0]
    ts = np.arange(1, total + 1) if steps is None else np.asarray(sorted(set(steps)))
    if ts.min() < 1 or ts.max() > total:
        raise ValueError(f"--steps must lie in 1 … {total}, got {ts.tolist()}")
    task = build_task(cfg, device)
    chosen = designs[torch.as_tensor(ts - 1, device=device)]  # [S, E, ρ, ρ, ρ]
    rewards = score(task, chosen.reshape(-1, *chosen.shape[2:]), batch_size).reshape(len(ts), -1)
    meta = {"epoch": rec.epoch, "recorded_reward_mean": float(np.mean(rec.rewards)),
            "replayed_final_reward_mean": float(rewards[-1].mean()) if ts[-1] == total else float("nan")}
    return ts, rewards, meta


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    p.add_argument("--epoch", type=int, default=None, help="epoch to replay (default: each run's last recorded)")
    p.add_argument("--steps", type=int, nargs="+", default=None, help="design steps t to score (default: 1 … T)")
    p.add_argument("--device", default="cpu", help="torch device of the replay and the task (cpu | cuda[:i])")
    p.add_argument("--batch-size", type=int, default=1024, help="designs per task.reward call (simulation batch)")
    common.add_overrides(p, "for scoring")
    args = p.parse_args(argv)
    if args.batch_size < 1:
        raise SystemExit(f"--batch-size must be >= 1, got {args.batch_size}")
    plt = common.pyplot()
    device = torch.device(args.device)

    runs = common.find_runs(args.paths)
    results = [robustness(r, args.epoch, args.steps, device, args.batch_size, args.overrides) for r in runs]
    ts = results[0][0]
    if any(not np.array_equal(t, ts) for t, _, _ in results):
        raise ValueError("paths: the runs have different numbers of design steps T; replay them separately")
    pooled = np.concatenate([r for _, r, _ in results], axis=1)  # [S, trials × robots]
    mean, half = common.mean_band(pooled, axis=1)
    prov = common.provenance(runs)
    prov["replayed_epochs"] = " ".join(str(m["epoch"]) for _, _, m in results)
    if args.overrides:
        prov["overrides"] = " ".join(args.overrides)
    cols: dict[str, Sequence] = {"t": ts, "mean": mean, "lower": mean - half, "upper": mean + half,
                                 "n": np.full(len(ts), pooled.shape[1])}
    for i, (_, r, _) in enumerate(results):
        cols[f"trial{i}_mean"] = r.mean(axis=1)
    out = {"csv": common.write_csv(args.out / "robustness.csv", cols, prov)}

    fig, ax = plt.subplots(figsize=(6, 4))
    curve = common.Curve(epochs=ts, mean=mean, lower=mean - half, upper=mean + half, raw_mean=mean,
                         n_trials=cols["n"])
    common.plot_curve(ax, curve, label="designs cut after t actions")
    recorded = np.mean([m["recorded_reward_mean"] for _, _, m in results])
    ax.axhline(recorded, color="0.5", linestyle="--", linewidth=1, label="recorded reward (t = T)")
    ax.set_xlabel("design step t")
    ax.set_ylabel("reward")
    ax.set_title(f"Robustness: {len(runs)} trial(s) × {pooled.shape[1] // len(runs)} robots, 99 % band",
                 fontsize=10)
    ax.legend(fontsize=8)
    fig.text(0.01, -0.04, common.provenance_caption(prov), fontsize=6, color="0.4")
    out.update(zip(("png", "pdf"), common.save_figure(fig, args.out, "robustness"), strict=True))

    print(f"robustness: {len(runs)} trial(s), {pooled.shape[1]} robots, t = {ts[0]} … {ts[-1]}")
    for _, _, m in results:
        print(f"  epoch {m['epoch']}: recorded mean reward {m['recorded_reward_mean']:.4g}, "
              f"replayed at t = T {m['replayed_final_reward_mean']:.4g}")
    print("wrote " + ", ".join(str(v) for v in out.values()))
    return out


if __name__ == "__main__":
    common.run_cli(main)
