"""Paper Fig. 5 — critic accuracy: predicted V(s_T) of trained and untrained critics against the true reward.

    python -m experiments.critic runs/paper_locomotion/<sweep> --out figures/critic

As the authors computed it (spec ppo.md, last section): for each trial i, the critic of its last checkpoint
("trained", ``checkpoints/last.pt``) and the critic it started from ("untrained", ``checkpoints/epoch_000000.pt``,
the same config and seed). For every recorded epoch, every episode's final grid s_T (the state after the last
action, which the critic never saw in training) is evaluated by every critic. In-domain = critic i on trial i's
robots; out-of-domain = critic i on the other trials' robots (needs >= 2 trials). Per critic and epoch the means
of the true reward, V_trained, V_untrained and |V - r| are taken; across critics the mean and 99 % band, smoothed
±2 epochs. Writes ``critic.png``/``.pdf`` and ``critic.csv``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments import common

QUANTITIES = ("reward", "v_trained", "v_untrained", "err_trained", "err_untrained")
DOMAINS = ("in", "out")


def load_critic(path: Path, device: torch.device) -> torch.nn.Module:
    """The policy network of a training checkpoint (``freeform.checkpoint`` format), rebuilt from the file alone."""
    from freeform.agents import VoxelActorCritic
    from freeform.checkpoint import load_checkpoint

    state = load_checkpoint(path)
    net = VoxelActorCritic(**state["policy_kwargs"])
    net.load_state_dict(state["ppo"]["policy"])
    return net.to(device).eval()


def untrained_critic(run: Path, device: torch.device) -> torch.nn.Module:
    """The critic trial ``run`` started from: its epoch-0 checkpoint, else rebuilt from its config and seed the way
    ``freeform.train.build`` draws it (the network's initialisation is the first draw after seeding)."""
    from freeform.checkpoint import CHECKPOINT_DIR, numbered_name

    first = Path(run) / CHECKPOINT_DIR / numbered_name(0)
    if first.is_file():
        return load_critic(first, device)
    from freeform.agents import VoxelActorCritic
    from freeform.train import seed_everything

    cfg = common.run_config(run)
    seed_everything(int(cfg["seed"]))
    net = VoxelActorCritic(resolution=cfg["env"]["resolution"], materials=cfg["task"]["materials"],
                           hidden=cfg["agent"]["hidden"])
    return net.to(device).eval()


@torch.no_grad()
def values(net: torch.nn.Module, grids: np.ndarray, device: torch.device, batch_size: int) -> np.ndarray:
    """V(s) of ``grids`` ``[E, ρ, ρ, ρ] uint8`` -> ``[E] float64``, in batches."""
    out = [net(torch.as_tensor(grids[i:i + batch_size]).to(device))[2].double().cpu()
           for i in range(0, len(grids), batch_size)]
    return torch.cat(out).numpy() if out else np.zeros(0)


def evaluate(runs: Sequence[Path], device: torch.device, batch_size: int = 1024, every: int = 1
             ) -> tuple[np.ndarray, dict[str, dict[str, np.ndarray]]]:
    """``(epochs [E], {domain: {quantity: [n_critics, E]}})``; NaN where undefined (a missing epoch, or the
    out-of-domain set of a single trial)."""
    from freeform.checkpoint import CHECKPOINT_DIR, LAST
    from freeform.records import list_records, read_record, record_epoch

    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    trained = [load_critic(Path(r) / CHECKPOINT_DIR / LAST, device) for r in runs]
    untrained = [untrained_critic(r, device) for r in runs]
    files = [{record_epoch(p): p for p in list_records(r)} for r in runs]
    epochs = np.array(sorted(set().union(*files))[::every])
    n = len(runs)
    result = {d: {q: np.full((n, len(epochs)), np.nan) for q in QUANTITIES} for d in DOMAINS}
    for k, epoch in enumerate(epochs):
        recs = [read_record(f[epoch]) if epoch in f else None for f in files]
        # per[i][j] = (rewards, V_trained_i, V_untrained_i) on trial j's robots
        per: list[list[Any]] = [[None] * n for _ in range(n)]
        for j, rec in enumerate(recs):
            if rec is None or rec.num_episodes == 0:
                continue
            for i in range(n):
                per[i][j] = (rec.rewards.astype(np.float64), values(trained[i], rec.final_grids, device, batch_size),
                             values(untrained[i], rec.final_grids, device, batch_size))
        for i in range(n):
            for domain, js in (("in", [i]), ("out", [j for j in range(n) if j != i])):
                parts = [per[i][j] for j in js if per[i][j] is not None]
                if not parts:
                    continue
                r, vt, vu = (np.concatenate(x) for x in zip(*parts, strict=True))
                q = result[domain]
                q["reward"][i, k], q["v_trained"][i, k], q["v_untrained"][i, k] = r.mean(), vt.mean(), vu.mean()
                q["err_trained"][i, k] = np.abs(vt - r).mean()
                q["err_untrained"][i, k] = np.abs(vu - r).mean()
    return epochs, result


STYLE = {"reward": ("true reward", "0.35"), "v_trained": ("trained critic V(s_T)", "tab:blue"),
         "v_untrained": ("untrained critic V(s_T)", "tab:red"), "err_trained": ("trained |V - r|", "tab:blue"),
         "err_untrained": ("untrained |V - r|", "tab:red")}


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    p.add_argument("--device", default="auto", help="torch device for the critics: auto | cpu | cuda[:i]")
    p.add_argument("--batch-size", type=int, default=1024, help="grids per critic forward pass")
    p.add_argument("--every", type=int, default=1, help="use every n-th recorded epoch (1 = all, the paper's)")
    p.add_argument("--smooth", type=int, default=common.SMOOTH_HALF_WINDOW, help="moving-average half-width")
    args = p.parse_args(argv)
    if args.batch_size < 1:
        raise SystemExit(f"--batch-size must be >= 1, got {args.batch_size}")
    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          "cpu" if args.device == "auto" else args.device)
    plt = common.pyplot()

    runs = common.find_runs(args.paths)
    epochs, result = evaluate(runs, device, args.batch_size, args.every)
    curves = {d: {q: common.across_trials(v, epochs, args.smooth) for q, v in result[d].items()} for d in DOMAINS}
    prov = common.provenance(runs)
    cols: dict[str, Sequence] = {"epoch": epochs}
    for d in DOMAINS:
        cols[f"{d}_n_critics"] = curves[d]["reward"].n_trials
        for q, c in curves[d].items():
            cols.update({f"{d}_{q}_mean": c.mean, f"{d}_{q}_lower": c.lower, f"{d}_{q}_upper": c.upper,
                         f"{d}_{q}_raw_mean": c.raw_mean})
    out = {"csv": common.write_csv(args.out / "critic.csv", cols, prov)}

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for col, (d, title) in enumerate((("in", "A  in-domain (own trial's robots)"),
                                      ("out", "B  out-of-domain (sibling trials' robots)"))):
        top, bottom = axes[0, col], axes[1, col]
        top.set_title(title, loc="left", fontsize=10)
        if not np.isfinite(result[d]["reward"]).any():
            top.text(0.5, 0.5, "needs >= 2 trials", ha="center", va="center", transform=top.transAxes, color="0.5")
            continue
        for q in ("reward", "v_trained", "v_untrained"):
            label, color = STYLE[q]
            common.plot_curve(top, curves[d][q], label=label, color=color)
        for q in ("err_trained", "err_untrained"):
            label, color = STYLE[q]
            common.plot_curve(bottom, curves[d][q], label=label, color=color)
        top.set_ylabel("reward / predicted reward")
        bottom.set_ylabel("|V(s_T) - reward|")
        bottom.set_xlabel("epoch")
        top.legend(fontsize=8)
        bottom.legend(fontsize=8)
    fig.suptitle(f"Critic estimation of the reward, {len(runs)} trial(s), mean and 99 % band", fontsize=11)
    fig.text(0.01, -0.01, common.provenance_caption(prov), fontsize=6, color="0.4")
    fig.tight_layout()
    out.update(zip(("png", "pdf"), common.save_figure(fig, args.out, "critic"), strict=True))

    tail = max(1, len(epochs) // 10)
    print(f"critic: {len(runs)} trial(s), {len(epochs)} epoch(s); mean |V - r| over the last {tail} epoch(s):")
    for d in DOMAINS:
        if np.isfinite(result[d]["reward"]).any():
            et = np.nanmean(result[d]["err_trained"][:, -tail:])
            eu = np.nanmean(result[d]["err_untrained"][:, -tail:])
            print(f"  {d}-domain: trained {et:.4g}, untrained {eu:.4g}")
    print("wrote " + ", ".join(str(v) for v in out.values()))
    return out


if __name__ == "__main__":
    common.run_cli(main)
