"""The dry run: what a launch would do — the jobs, each one's per-rank work split, the launch command — without
running or submitting anything (``freeform-train ... trainer.dry_run=true``; ``docs/scaling.md``).

The split follows the data-parallel rules of :mod:`freeform.agents.distributed`: rank r holds the contiguous
environments :func:`~freeform.agents.distributed.env_slice` gives it and computes its share of every global
minibatch (on average ``M·n_r/N`` samples, a random number that varies from minibatch to minibatch).
"""

from __future__ import annotations

import os
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from freeform._conf_dir import conf_dir
from freeform.agents.distributed import env_slice, launch_env
from freeform.config import TrainConfig, ppo_config

SLURM_LAUNCHER = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
LOCAL_LAUNCHER = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
# Hydra's keys of the submitit launcher -> sbatch's (submitit's own translation, SlurmExecutor._equivalence_dict).
_SBATCH_NAMES = {
    "name": "job_name",
    "timeout_min": "time",
    "mem_gb": "mem",
    "tasks_per_node": "ntasks_per_node",
}
_NOT_SBATCH = {"_target_", "submitit_folder", "max_num_timeout"}


def describe_split(cfg: TrainConfig, world_size: int, ranks_per_node: int | None = None) -> str:
    """The per-rank work split of one run of ``cfg`` over ``world_size`` ranks, as a table (text)."""
    n, steps = cfg.env.num_envs, ppo_config(cfg, device="cpu").rollout_steps
    if world_size > n:
        raise ValueError(f"env.num_envs ({n}) must be >= the number of ranks ({world_size}): every rank needs an env")
    per_node = ranks_per_node or world_size
    batch = n * steps
    minibatch = min(cfg.agent.sgd_minibatch_size, batch)
    lines = [
        f"run {cfg.name!r} seed {cfg.seed}: {world_size} rank(s), {per_node} per node",
        f"  global batch N x T = {n} x {steps} = {batch} samples per epoch; minibatch M = {minibatch} -> "
        f"{batch // minibatch} minibatches per pass ({batch % minibatch} samples dropped), "
        f"{cfg.agent.num_sgd_iter} passes = {cfg.agent.num_sgd_iter * (batch // minibatch)} all-reduces per epoch",
        f"  device {cfg.trainer.device!r}: "
        + (
            "rank r uses GPU (r mod ranks-per-node) of its node, alone (CUDA_VISIBLE_DEVICES narrowed), NCCL"
            if cfg.trainer.device != "cpu"
            else "CPU, gloo"
        )
        + (" (CPU + gloo where no GPU is present)" if cfg.trainer.device == "auto" else ""),
        f"  {'rank':>4}  {'local':>5}  {'envs':>13}  {'count':>5}  {'samples/epoch':>13}  {'minibatch share (mean)':>22}",
    ]
    for r in range(world_size):
        lo, hi = env_slice(n, world_size, r)
        share = minibatch * (hi - lo) / n
        lines.append(
            f"  {r:>4}  {r % per_node:>5}  {f'[{lo}, {hi})':>13}  {hi - lo:>5}  {(hi - lo) * steps:>13}  {share:>22.1f}"
        )
    return "\n".join(lines)


def _strip_dry_run(overrides: Sequence[str]) -> list[str]:
    return [o for o in overrides if o.split("=", 1)[0].lstrip("+") != "trainer.dry_run"]


def _job_overrides(argv: Sequence[str]) -> tuple[bool, list[str], list[list[str]]]:
    """(multirun, the command line's overrides, the overrides of every job) — Hydra's basic sweeper's expansion."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    multirun = any(a in ("-m", "--multirun") for a in argv)
    overrides = [a for a in argv if not a.startswith("-")]
    if not multirun:
        return False, overrides, [overrides]
    parsed = OverridesParser.create().parse_overrides(overrides)
    batches = BasicSweeper.split_arguments(parsed, None)
    return True, overrides, [job for batch in batches for job in batch]


def _sbatch_script(launcher: dict[str, Any], jobs: int) -> str:
    """The sbatch file submitit would write for this launcher config (an array of ``jobs`` tasks)."""
    from submitit.slurm.slurm import _make_sbatch_string  # a private helper: the dry run only prints its text

    params: dict[str, Any] = {}
    for key, value in launcher.items():
        if key in _NOT_SBATCH or value is None:
            continue
        name = _SBATCH_NAMES.get(key, key)
        params[name] = f"{int(value)}GB" if name == "mem" and value == int(value) else value
    if jobs > 1:
        params["map_count"] = jobs
    folder = str(launcher.get("submitit_folder", ".submitit/%j"))
    command = " ".join([shlex.quote(sys.executable), "-u -m submitit.core._submit", shlex.quote(folder)])
    return _make_sbatch_string(command=command, folder=folder, **params)


def dry_run(argv: Sequence[str], config_dir: str | os.PathLike[str] | None = None) -> str:
    """The dry-run report of ``freeform-train *argv`` (text): jobs, per-rank splits and the launch command.

    ``config_dir``: the Hydra configs to compose (default: :func:`freeform._conf_dir.conf_dir`, freeform-train's)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.utils import setup_globals
    from omegaconf import OmegaConf

    from freeform.config import to_dataclass

    multirun, overrides, jobs = _job_overrides(argv)
    GlobalHydra.instance().clear()
    launched = launch_env()
    out: list[str] = []
    launcher: dict[str, Any] = {}
    previous: list[str] = []
    setup_globals()  # Hydra's ``now`` resolver, used by the sweep directory
    config_dir = conf_dir() if config_dir is None else config_dir
    with initialize_config_dir(config_dir=str(Path(config_dir).resolve()), version_base="1.3", job_name="train"):
        for i, job in enumerate(jobs):
            with_hydra = compose("config", overrides=_strip_dry_run(job), return_hydra_config=True)
            try:  # the sweep directory (with its timestamp) and the job name, as a launch would resolve them
                launcher = OmegaConf.to_container(with_hydra.hydra.launcher, resolve=True)  # type: ignore[assignment]
            except Exception:
                launcher = OmegaConf.to_container(with_hydra.hydra.launcher, resolve=False)  # type: ignore[assignment]
            target = str(launcher.get("_target_", ""))
            if target in (SLURM_LAUNCHER, LOCAL_LAUNCHER):
                world = int(launcher.get("nodes") or 1) * int(launcher.get("tasks_per_node") or 1)
                per_node = int(launcher.get("tasks_per_node") or 1)
            elif launched is not None:
                world, per_node = launched["world_size"], launched["local_world_size"]
            else:
                world, per_node = 1, 1
            cfg = to_dataclass(compose("config", overrides=[o for o in _strip_dry_run(job) if not o.startswith("hydra")]))
            label = " ".join(_strip_dry_run(job)) or "(no overrides)"
            out.append(f"job {i}: {label}")
            split = describe_split(cfg, world, per_node).split("\n")
            if split[1:] == previous[1:]:
                out.extend([split[0], "  (the same split as the job above)"])
            else:
                out.extend(split)
            previous = split
    out.append("")
    out.extend(_launch_lines(launcher, launched, len(jobs), multirun, _strip_dry_run(overrides)))
    return "\n".join(out)


def _launch_lines(launcher: dict[str, Any], launched: dict[str, Any] | None, jobs: int, multirun: bool,
                  clean: list[str]) -> list[str]:
    """How the dry run's ``jobs`` would be launched: through the submitit ``launcher`` (SLURM or local), under
    torchrun (``launched``: its environment), or as one ``freeform-train``; ``clean`` the overrides."""
    out: list[str] = []
    target = str(launcher.get("_target_", ""))
    if target == SLURM_LAUNCHER:
        out.append(f"launch: {jobs} SLURM job(s) as one array through submitit; each task runs the Hydra job:")
        try:
            out.append(_sbatch_script(launcher, jobs))
        except Exception as exc:  # a submitit version without the helper: list the parameters instead
            out.append(f"(sbatch text unavailable: {type(exc).__name__}: {exc})")
            out.extend(f"  {k}: {v}" for k, v in launcher.items())
        out.append("submit for real: freeform-train " + " ".join(["-m"] * multirun + clean))
    elif target == LOCAL_LAUNCHER:
        out.append(f"launch: {jobs} local submitit job(s), each a subprocess with these resources:")
        out.extend(f"  {k}: {v}" for k, v in launcher.items() if k != "_target_")
        out.append("run for real: freeform-train " + " ".join(["-m"] * multirun + clean))
    else:
        args = " ".join(["-m"] * multirun + clean)
        if launched is not None:
            nodes = max(1, launched["world_size"] // max(1, launched["local_world_size"]))
            out.append(
                f"launch: torchrun --nnodes={nodes} --nproc_per_node={launched['local_world_size']} -m freeform.train {args}"
            )
        else:
            out.append(f"launch: freeform-train {args}".rstrip())
            out.append(f"  one run on G GPUs of a node: torchrun --standalone --nproc_per_node=G -m freeform.train {args}".rstrip())
    return out


__all__ = ["describe_split", "dry_run"]
