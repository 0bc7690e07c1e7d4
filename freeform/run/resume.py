"""Continuing a run: which checkpoint (``trainer.resume``), read before anything in the run directory is opened, and
the config it continues with (the checkpoint's own; only ``trainer.*`` and what PPO's evaluation reports may differ)."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from freeform.agents import distributed
from freeform.checkpoint import (
    AUTO,
    CHECKPOINT_DIR,
    LAST,
    CheckpointError,
    auto_checkpoint,
    load_checkpoint,
    resolve_checkpoint,
)
from freeform.config import TrainConfig, flatten, from_container, to_container, validate

log = logging.getLogger("freeform.train")


def find_checkpoint(cfg: TrainConfig, run_dir: Path) -> Path | None:
    """The checkpoint ``trainer.resume`` names: ``auto`` -> this run directory's ``last.pt`` if there is one (rank
    0 looks; every rank gets its answer), a run directory or file -> that one, None -> none."""
    if cfg.trainer.resume == AUTO:
        found = auto_checkpoint(run_dir) if distributed.is_main_process() else None
        found = distributed.broadcast_object(str(found) if found is not None else None)
        if found is None:
            log.info("trainer.resume=auto: no %s/%s in %s, starting a new run", CHECKPOINT_DIR, LAST, run_dir)
        return Path(found) if found is not None else None
    return resolve_checkpoint(cfg.trainer.resume) if cfg.trainer.resume else None


def read_checkpoint(path: Path, cfg: TrainConfig, overrides: Sequence[str] | None) -> tuple[dict[str, Any], TrainConfig]:
    """The run checkpoint at ``path`` and the config the run continues with (:func:`resume_config`); a bad file is
    a ``CheckpointError`` naming it, and nothing is lost."""
    state = load_checkpoint(path)
    try:
        saved = from_container(state["config"])
    except (ValueError, KeyError) as exc:
        raise CheckpointError(f"checkpoint {path}: its config is unusable: {exc}") from exc
    return state, resume_config(saved, cfg, overrides)


def override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("~+")


# How a run is executed and reported, not what it trains: these keys name no job of a sweep and no cache of runs
# (a run continued with more threads or another print interval is the same run).
EXECUTION_KEYS = frozenset({"trainer.device", "trainer.progress", "trainer.threads", "trainer.print_every"})


# What a run reports, not what it trains: PPO's deterministic evaluation draws from none of the training's generators
# (a run with it trains what one without does, bit for bit), so a resumed run may start, stop or change it — a run
# trained under one plateau rule can be continued under another (trainer.plateau_on=eval_return).
REPORTING_FIELDS = ("eval_every", "eval_episodes", "eval_same_episodes")
REPORTING_KEYS = frozenset(f"agent.{field}" for field in REPORTING_FIELDS)


def resume_config(saved: TrainConfig, current: TrainConfig, overrides: Sequence[str] | None) -> TrainConfig:
    """The config of a resumed run: the checkpoint's own, with the ``trainer`` fields given on the command line.

    ``overrides`` (Hydra's command-line overrides) name what the user set; ``None`` (Python use) takes the whole
    ``trainer`` section of ``current``. The evaluation's keys (:data:`REPORTING_KEYS`) go together: where any of
    them or ``trainer.plateau_on`` is named, all three are ``current``'s (its preset's evaluation with them), so that
    a rule taken up on resume reads the evaluation the preset defines, not a half of the checkpoint's. Any other
    explicitly set key must equal the checkpoint's value: changing what the run trains mid-way would break the promise
    that a resumed run equals an uninterrupted one.
    """
    trainer = dataclasses.replace(saved.trainer, resume=current.trainer.resume)
    reported = {field: getattr(current.agent, field) for field in REPORTING_FIELDS}
    if overrides is None:
        return validate(dataclasses.replace(saved, trainer=dataclasses.replace(current.trainer),
                                            agent=dataclasses.replace(saved.agent, **reported)))
    named = {override_key(o) for o in overrides}
    agent = dataclasses.replace(saved.agent, **reported) if named & (REPORTING_KEYS | {"trainer.plateau_on"}) else (
        saved.agent)
    saved_flat, current_flat = flatten(to_container(saved)), flatten(to_container(current))
    for override in overrides:
        key = override_key(override)
        if key.startswith("hydra.") or key == "trainer.resume":
            continue
        if key.startswith("trainer."):
            field = key.split(".", 1)[1]
            trainer = dataclasses.replace(trainer, **{field: getattr(current.trainer, field)})
        elif key in REPORTING_KEYS:
            continue  # (taken with the others, above)
        elif key == "experiment":
            if current.name != saved.name:
                raise ValueError(f"experiment: the run being resumed is {saved.name!r}, not {current.name!r}")
        else:
            changed = [k for k in current_flat if (k == key or k.startswith(key + ".")) and current_flat[k] != saved_flat.get(k)]
            if changed:
                raise ValueError(f"{key}: cannot change {changed[0]} when resuming ({saved_flat.get(changed[0])!r} in "
                                 f"the checkpoint); only trainer.* and {', '.join(sorted(REPORTING_KEYS))} may "
                                 "differ")
    return validate(dataclasses.replace(saved, trainer=trainer, agent=agent))


__all__ = ["EXECUTION_KEYS", "REPORTING_KEYS", "find_checkpoint", "override_key", "read_checkpoint", "resume_config"]
