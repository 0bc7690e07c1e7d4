"""``freeform-train`` / ``python -m freeform.train``: the Hydra application over ``conf/``.

    freeform-train                                   # the CPU demo (experiment=volume_cpu)
    freeform-train experiment=paper_volume           # paper Table I, volume
    freeform-train -m experiment=paper_volume seed=0,1,2,3,4   # five trials, one directory each
    freeform-train trainer.resume=runs/volume_cpu/2026-01-01_12-00-00 trainer.epochs=80
    freeform-train hydra.run.dir=runs/mine      # again after a kill or SIGTERM: continues (trainer.resume=auto)
    torchrun --nproc_per_node=4 -m freeform.train experiment=paper_locomotion   # one run on 4 GPUs (docs/scaling.md)
    freeform-train trainer.dry_run=true ...          # print the jobs, the per-rank split and the launch command
    freeform-train algo=ga                           # an evolutionary baseline instead of PPO (algo=cmaes, grid_ga)

Exit status: 0 done; 1 with a one-line ``freeform-train: error: ...`` for bad input or a failed write; 75 ("requeue
me") when stopped by SIGTERM/SIGUSR2 after checkpointing (``freeform.preemption``).
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from freeform import preemption
from freeform._conf_dir import conf_dir
from freeform.agents import distributed
from freeform.checkpoint import AUTO, CheckpointError, auto_checkpoint, run_dir_of
from freeform.config import register_configs, to_dataclass
from freeform.run.resume import EXECUTION_KEYS, override_key
from freeform.run.trainer import train

log = logging.getLogger("freeform.train")

CONF_DIR = conf_dir()  # the installed package data or the checkout's conf/ (freeform/_conf_dir.py)
SWEPT_KEYS_ENV = "FREEFORM_SWEPT_KEYS"


# ------------------------------------------------------------------------------------------------ Hydra resolvers


def _secondary_rank_dir() -> Path:
    """Where Hydra may put a rank > 0's own output (its log, before it is silenced): a scratch directory, removed
    at the end; the run directory is rank 0's, and its timestamp could differ from this rank's by a second."""
    return Path(tempfile.gettempdir()) / f"freeform-rank{distributed.launch_rank()}-{os.getpid()}"


def _resolver_run_dir(resume: str | None, default: str) -> str:
    """``hydra.run.dir``: the resumed run's directory (``trainer.resume=<run or file>``), else ``default``
    (runs/<experiment>/<timestamp>, or what ``hydra.run.dir`` says: ``trainer.resume=auto`` continues whatever
    directory that is); a scratch directory on ranks > 0 of a data-parallel run (rank 0's run directory is
    broadcast to them)."""
    if distributed.launch_rank() > 0:
        return str(_secondary_rank_dir())
    return str(run_dir_of(resume)) if resume and resume != AUTO else default


def _resolver_hydra_subdir(resume: str | None, output_dir: str | None = None) -> str | None:
    """``hydra.output_subdir``: keep the original run's ``.hydra`` when resuming in its directory (an explicit
    ``trainer.resume``, or ``auto`` where the job's directory ``output_dir`` has a checkpoint); none on ranks > 0
    of a data-parallel run (rank 0 writes it)."""
    if distributed.launch_rank() > 0:
        return None
    if resume == AUTO:
        resuming = output_dir is not None and auto_checkpoint(output_dir) is not None
    else:
        resuming = bool(resume)
    return f".hydra/resume_{datetime.now():%Y-%m-%d_%H-%M-%S}" if resuming else ".hydra"


def _swept_keys(argv: Sequence[str]) -> set[str]:
    """The keys a command line sweeps over (``seed=0,1,2`` -> ``{"seed"}``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides([a for a in argv if not a.startswith("-")])
        return {o.key_or_group for o in parsed if o.is_sweep_override()}
    except Exception:  # an argument Hydra's grammar rejects: Hydra itself reports it
        return set()


def _resolver_sweep_subdir(job_overrides: Sequence[str], exclude: Sequence[str]) -> str:
    """``hydra.sweep.subdir``: the job's values of the *swept* keys, e.g. ``seed=3`` for ``-m seed=0,1,2,3,4``.

    Hydra's ``override_dirname`` names every override, swept or not; which keys are swept is read from the command
    line (``sys.argv``) — or from ``FREEFORM_SWEPT_KEYS``, which :func:`main` sets for jobs that run in other
    processes (the submitit launchers). Without a sweep, every override except ``exclude`` and the execution keys
    (``EXECUTION_KEYS``: threads, device, progress, print interval) names the job.
    """
    if SWEPT_KEYS_ENV in os.environ:
        swept = {k for k in os.environ[SWEPT_KEYS_ENV].split(",") if k}
    else:
        swept = _swept_keys(sys.argv[1:])
    keys = [(override_key(o), o) for o in job_overrides]
    chosen = [o for k, o in keys if k in swept] or [o for k, o in keys if k not in EXECUTION_KEYS | set(exclude)]
    return ",".join(sorted(chosen)).replace("/", "_") or "default"


def register_resolvers() -> None:
    """The resolvers ``conf/config.yaml``'s ``hydra`` section names, and the config schema (idempotent)."""
    OmegaConf.register_new_resolver("freeform_sweep_subdir", _resolver_sweep_subdir, replace=True)
    OmegaConf.register_new_resolver("freeform_run_dir", _resolver_run_dir, replace=True)
    OmegaConf.register_new_resolver("freeform_hydra_subdir", _resolver_hydra_subdir, replace=True)
    register_configs()


# A submitit launcher's job runs in its own process, which unpickles _hydra_entry (importing this module) and then
# resolves hydra.sweep.subdir before calling it: the resolvers must exist once this module is imported. Only the
# command-line module registers them; importing the library (freeform.run.trainer, ...) changes no global state.
register_resolvers()


# ------------------------------------------------------------------------------------------------ the entry


def _hydra_entry(cfg: Any) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from tqdm.contrib.logging import logging_redirect_tqdm

    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    try:
        typed = to_dataclass(cfg)
        # torchrun / a multi-task SLURM step: join the process group (rank r on GPU r); ranks > 0 stay quiet.
        if not typed.trainer.dry_run and distributed.init_from_env() and not distributed.is_main_process():
            _silence_secondary_rank()
        with logging_redirect_tqdm():
            result = train(typed, run_dir, overrides=list(hydra_cfg.overrides.task))
        if hydra_cfg.mode != RunMode.MULTIRUN or result.stopped:  # a sweep's next job in this process reuses the group
            distributed.shutdown()  # every rank finished: tear the process group down together
    except (ValueError, CheckpointError) as exc:
        # A clear one-line message (and a non-zero exit), not a traceback through Hydra's internals.
        raise SystemExit(f"freeform-train: error: {exc}") from exc
    if result.stopped:
        # Stopped by a signal, checkpoint written: exit 75 "requeue me" (or submitit's handler requeues the job).
        preemption.exit_for_requeue(result.stop_signal)
    if not distributed.is_main_process() or typed.trainer.dry_run:
        return
    log.info("done: %d epochs, %d steps, run directory %s", result.epochs, result.global_step, run_dir)
    curve = [h["charts/episode_reward_mean"] for h in result.history if "charts/episode_reward_mean" in h]
    if len(curve) >= 2:
        last = curve[-min(5, len(curve) - 1) :]
        first, tail = curve[0], sum(last) / len(last)
        log.info("episode reward mean: first epoch of this call %.2f -> last %d epochs %.2f (x%.2f)",
                 first, len(last), tail, tail / first if first else float("nan"))


def _silence_secondary_rank() -> None:
    """A rank > 0 logs warnings to the console only: rank 0 writes the run's log."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if isinstance(handler, logging.FileHandler):
            root.removeHandler(handler)
            handler.close()
    root.setLevel(logging.WARNING)
    scratch = _secondary_rank_dir()
    if scratch.is_dir():
        shutil.rmtree(scratch, ignore_errors=True)


def _dry_run_requested(argv: Sequence[str]) -> bool:
    return any(a.split("=", 1)[0].lstrip("+") == "trainer.dry_run" and a.split("=", 1)[1].lower() in ("true", "1", "yes")
               for a in argv if "=" in a)


def presets_with(section: str, conf: Path) -> list[str]:
    """The experiment presets (``conf/experiment/*.yaml``) that set ``section``, themselves or through a preset
    they build on (their ``defaults`` list)."""
    files = {p.stem: OmegaConf.load(p) for p in sorted((conf / "experiment").glob("*.yaml"))}

    def sets(name: str, seen: frozenset[str] = frozenset()) -> bool:
        preset = files.get(name)
        if preset is None or name in seen:
            return False
        bases = [d for d in preset.get("defaults", []) if isinstance(d, str) and d != "_self_"]
        return section in preset or any(sets(b, seen | {name}) for b in bases)

    return [name for name in files if sets(name)]


def _empty_section_overrides(argv: Sequence[str], conf: Path) -> str | None:
    """What is wrong, in words, when ``argv`` overrides a field of a section that the chosen experiment leaves
    empty (``control.*`` without a control experiment: Hydra itself fails there with an assertion about a
    ``NoneType`` root), naming the experiments that have it; None otherwise. Sweeps and ``+``/``~`` overrides are
    left to Hydra."""
    import dataclasses

    from hydra.core.override_parser.overrides_parser import OverridesParser

    from freeform.config import TrainConfig, compose_raw

    optional = {f.name for f in dataclasses.fields(TrainConfig) if f.default is None}
    try:
        parsed = OverridesParser.create().parse_overrides([a for a in argv if not a.startswith("-")])
    except Exception:  # (Hydra reports a malformed override itself)
        return None
    touched = sorted({o.key_or_group.split(".")[0] for o in parsed if "." in o.key_or_group
                      and o.key_or_group.split(".")[0] in optional
                      and not (o.is_add() or o.is_force_add() or o.is_delete())})
    groups = [o for o in parsed if "." not in o.key_or_group]
    if not touched or any(o.is_sweep_override() for o in groups):
        return None
    try:
        cfg = compose_raw(*(o.input_line for o in groups))
    except Exception:  # (Hydra reports a bad group choice itself)
        return None
    empty = [s for s in touched if cfg.get(s) is None]
    if not empty:
        return None
    section, having = empty[0], presets_with(empty[0], conf)
    example = f"{section}_population_cpu" if f"{section}_population_cpu" in having else having[0]
    return (f"{section}.* overridden, but experiment={cfg.get('name')} has no {section} section (not a {section} "
            f"experiment): choose one that has, e.g. experiment={example} — {', '.join(having)}")

def main() -> None:
    """Console entry point ``freeform-train`` (Hydra parses ``sys.argv``).

    ``trainer.dry_run=true`` on the command line is answered here, before Hydra launches anything (a sweep on the
    submitit launcher would submit jobs): the jobs, each one's per-rank split and the launch command are printed.
    """
    import hydra

    register_resolvers()
    # conf/hydra/launcher/submitit_*.yaml carry the names the plugin registers its typed schemas under, so Hydra
    # checks them against those schemas (what we want) and warns that such matching is deprecated.
    warnings.filterwarnings(
        "ignore", message=r"\s*'hydra/launcher/submitit_\w+' is validated against ConfigStore schema", category=UserWarning
    )
    # Jobs of the submitit launchers resolve hydra.sweep.subdir in their own processes, whose argv is submitit's.
    os.environ[SWEPT_KEYS_ENV] = ",".join(sorted(_swept_keys(sys.argv[1:])))
    if message := _empty_section_overrides(sys.argv[1:], CONF_DIR):
        print(f"freeform-train: error: {message}", file=sys.stderr)
        raise SystemExit(1)
    if _dry_run_requested(sys.argv[1:]):
        from freeform.launch import dry_run

        text = dry_run(sys.argv[1:], CONF_DIR)
        if distributed.launch_rank() == 0:
            print(text, flush=True)
        return

    hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")(_hydra_entry)()


__all__ = ["CONF_DIR", "SWEPT_KEYS_ENV", "main", "register_resolvers"]
