"""``freeform-train`` / ``python -m freeform.train`` and the names scripts import from here: the application lives
in ``freeform.run`` (``docs/architecture.md``); this module keeps its public names where they always were.

Python use: ``train(cfg, run_dir)`` with a :class:`freeform.config.TrainConfig`; ``@register_task("name")`` adds a
task, ``@register_learner("name")`` an algorithm.
"""

from __future__ import annotations

from typing import Any

from freeform.config import TrainConfig
from freeform.run.build import (
    LEARNERS,
    TASKS,
    build,
    build_task,
    register_learner,
    register_task,
    resolve_device,
    seed_everything,
)
from freeform.run.resume import resume_config
from freeform.run.rundir import RUN_INFO, run_info
from freeform.run.trainer import (
    EpochCallback,
    EpochContext,
    TrainResult,
    default_callbacks,
    render_callback,
    train,
)

__all__ = ["LEARNERS", "RUN_INFO", "TASKS", "EpochCallback", "EpochContext", "TrainConfig", "TrainResult", "build",
           "build_task", "default_callbacks", "register_learner", "register_task", "render_callback", "resolve_device",
           "resume_config", "run_info", "seed_everything", "train"]  # and, when asked, the command line's (_CLI)

_CLI = ("CONF_DIR", "SWEPT_KEYS_ENV", "_resolver_hydra_subdir", "_resolver_run_dir", "_resolver_sweep_subdir", "main")


def __getattr__(name: str) -> Any:
    """The command line's names, imported when asked: importing the library registers no Hydra resolver."""
    if name in _CLI:
        from freeform.run import cli

        return getattr(cli, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if __name__ == "__main__":
    from freeform.run.cli import main

    main()
