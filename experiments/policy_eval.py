"""Untrained vs trained policy: fresh designs sampled from a run's checkpoints, scored by the run's own task.

    python -m experiments.policy_eval runs/locomotion_cpu/<run> --out figures/policy_eval --episodes 128

For each run and each checkpoint (default: ``epoch_000000.pt``, the untrained policy, and ``last.pt``), the policy
designs ``--episodes`` robots (actions sampled from its Gaussian as in training, or its mean with
``--deterministic``), the run's task scores them (locomotion: simulated with the run's protocol), and the mean
reward with its 99 % band and the mean body metrics are reported. Unlike the training curve, these are new designs
of a fixed policy, all scored after training, so the two policies are compared on equal terms. ``--set KEY=VALUE``
scores them under another protocol than the run trained with (dotted keys of its config, as
``experiments.rescore``), e.g. ``--set sim.burn_in=3.0``: is what the policy learned still there once every body has
landed? Writes ``policy_eval.csv``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments import common


@torch.no_grad()
def design(cfg: Any, checkpoint: Path, episodes: int, seed: int, deterministic: bool, device: torch.device
           ) -> dict[str, np.ndarray]:
    """Roll the checkpoint's policy out for one episode in ``episodes`` environments: ``rewards [E]`` and the body
    metrics ``{name: [E]}`` of the final designs."""
    from experiments.critic import load_critic
    from freeform.run.build import design_env

    env = design_env(cfg, device, episodes, cfg.seed)
    policy = load_critic(checkpoint, device)
    generator = torch.Generator(device=device).manual_seed(seed)
    obs = env.reset()
    for _ in range(env.steps):
        mean, log_std, _ = policy(obs)
        noise = torch.randn(mean.shape, generator=generator, device=device)
        action = mean if deterministic else mean + log_std.exp() * noise
        obs, reward, done, info = env.step(action)
    assert bool(done.all())
    return {"reward": reward.double().cpu().numpy(),
            **{k: v.double().cpu().numpy() for k, v in info.get("metrics", {}).items()}}


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    p = common.base_parser(__doc__.splitlines()[0])
    p.add_argument("--checkpoints", nargs="+", default=["epoch_000000.pt", "last.pt"],
                   help="checkpoint file names inside each run's checkpoints/ (default: untrained and last)")
    p.add_argument("--episodes", type=int, default=128, help="designs per policy")
    p.add_argument("--seed", type=int, default=12345, help="seed of the action noise (the same for every policy)")
    p.add_argument("--deterministic", action="store_true", help="use the policy's mean action")
    p.add_argument("--device", default="cpu", help="torch device (cpu | cuda[:i])")
    common.add_overrides(p, "to design and score under")
    args = p.parse_args(argv)
    if args.episodes < 1:
        raise SystemExit(f"--episodes must be >= 1, got {args.episodes}")
    from experiments.robustness import run_train_config
    from freeform.checkpoint import CHECKPOINT_DIR, load_checkpoint

    device = torch.device(args.device)
    runs = common.find_runs(args.paths)
    rows: dict[str, list] = {"run": [], "checkpoint": [], "epoch": [], "n": [], "reward_mean": [],
                             "reward_lower": [], "reward_upper": []}
    metric_rows: dict[str, list] = {}
    for run in runs:
        cfg = run_train_config(run, args.overrides)
        for name in args.checkpoints:
            path = run / CHECKPOINT_DIR / name
            if not path.is_file():
                raise SystemExit(f"--checkpoints: {path} does not exist")
            result = design(cfg, path, args.episodes, args.seed, args.deterministic, device)
            mean, half = common.mean_band(result["reward"])
            rows["run"].append(str(run))
            rows["checkpoint"].append(name)
            rows["epoch"].append(int(load_checkpoint(path)["epoch"]))
            rows["n"].append(args.episodes)
            rows["reward_mean"].append(float(mean))
            rows["reward_lower"].append(float(mean - half))
            rows["reward_upper"].append(float(mean + half))
            for k, v in result.items():
                if k != "reward":
                    metric_rows.setdefault(f"{k}_mean", []).append(float(v.mean()))
            print(f"{run.name} {name:18s} epoch {rows['epoch'][-1]:5d}: reward {mean:.3f} ± {half:.3f} "
                  f"(99 %, n = {args.episodes})" + "".join(f", {k} {v.mean():.3g}" for k, v in result.items()
                                                         if k in ("volume", "lcc_ratio")))
    prov = common.provenance(runs)
    prov["action_noise"] = "mean action" if args.deterministic else f"sampled, seed {args.seed}"
    if args.overrides:
        prov["overrides"] = " ".join(args.overrides)
    out = {"csv": common.write_csv(args.out / "policy_eval.csv", {**rows, **metric_rows}, prov)}
    print("wrote " + str(out["csv"]))
    return out


if __name__ == "__main__":
    common.run_cli(main)
