"""The application: a run of any learner on a design task, from its config to its run directory.

Data flows down the list; each module has one job:

- ``build``    task, env and learner from one registry each (``register_task``, ``register_learner``)
- ``resume``   which checkpoint ``trainer.resume`` names, and the config a resumed run continues with
- ``rundir``   the run directory (``run_info.json``, checkpoints, records) with one failure policy
- ``trainer``  ``Trainer.run()``: start -> while going on: train one epoch -> write it -> checkpoint -> result
- ``cli``      the Hydra entry point ``freeform-train``

``freeform.train`` re-exports what scripts use (``train``, ``main``, ``register_task`` ...).
"""

from freeform.run.build import build, build_task, register_learner, register_task
from freeform.run.trainer import EpochCallback, EpochContext, Trainer, TrainResult, train

__all__ = ["EpochCallback", "EpochContext", "TrainResult", "Trainer", "build", "build_task", "register_learner",
           "register_task", "train"]
