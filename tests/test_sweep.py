"""Sweeps through Hydra's submitit launcher, and the dry run that checks a launch before it spends GPU hours.

The ``submitit_local`` sweep really runs (two seeds as two local submitit jobs). SLURM cannot run here, so its
launcher config is checked through the dry run: the sbatch file submitit would submit, with the overridden keys.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import run_cli as cli  # tests/helpers.py
from helpers import tiny

from freeform import train as train_mod
from freeform.checkpoint import load_checkpoint
from freeform.config import TrainConfig
from freeform.launch import describe_split
from freeform.records import list_records, read_record

pytestmark = pytest.mark.usefixtures("keep_global_rng")  # tests/conftest.py

TINY = tiny("trainer.checkpoint_every=0")


# Injected into the submitit jobs' interpreters (PYTHONPATH): each job's first start is sent SIGUSR2 — what SLURM and
# submitit send before a time limit — from its epoch-0 callback; a marker file in the run directory makes it once.
INTERRUPT_ONCE = """
import os
if os.environ.get("SUBMITIT_LOCAL_JOB_ID"):  # a submitit_local job's task (not its controller)
    import signal
    from freeform.run import trainer

    _default_callbacks = trainer.default_callbacks

    def _interrupt_once(cfg):
        def callback(ctx):
            marker = ctx.run_dir / "interrupted_once"
            if ctx.epoch == 0 and not marker.exists():
                marker.write_text(str(os.getpid()))
                signal.raise_signal(signal.SIGUSR2)
        return [*_default_callbacks(cfg), callback]

    trainer.default_callbacks = _interrupt_once
"""


@pytest.mark.slow
def test_submitit_local_sweep_over_two_seeds_completes_after_interrupting_each_job(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two seeds as two submitit jobs, each sent SIGUSR2 during its first epoch: each stops after that epoch's
    checkpoint, submitit requeues it (its handler, called by freeform once the checkpoint is written), and the
    requeued job — the same pickled command, the same run directory, trainer.resume=auto — finishes the run. No
    hand-made resume; the sweep directory (a timestamp resolved once, at launch) is the same for both starts."""
    pytest.importorskip(
        "hydra_plugins.hydra_submitit_launcher", reason="the submitit launcher is the 'cluster' extra (also in 'dev')"
    )
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(INTERRUPT_ONCE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(hook), os.environ.get("PYTHONPATH")) if p))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.chdir(tmp_path)  # the sweep goes to runs/volume_cpu/<timestamp>/ here
    cli(monkeypatch, "-m", "hydra/launcher=submitit_local", "seed=0,1", *TINY, "trainer.epochs=2")

    (sweep,) = (tmp_path / "runs" / "volume_cpu").iterdir()
    runs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert runs == ["seed=0", "seed=1"]  # named by the swept key, as with the basic launcher
    for r in runs:
        info = json.loads((sweep / r / "run_info.json").read_text())
        assert (sweep / r / "interrupted_once").is_file()  # the first start was signalled ...
        assert [x["epoch"] for x in info["resumes"]] == [1]  # ... stopped after epoch 1, resumed by itself
        assert load_checkpoint(sweep / r / "checkpoints" / "last.pt")["epoch"] == 2
        assert [p.name for p in list_records(sweep / r)] == ["epoch_000000.npz", "epoch_000001.npz"]
    assert [json.loads((sweep / r / "run_info.json").read_text())["seed"] for r in runs] == [0, 1]
    a, b = (read_record(sweep / r / "records" / "epoch_000001.npz") for r in runs)
    assert a.actions.shape == (4, 5, 3 + 2)
    assert not np.array_equal(a.actions, b.actions)
    # Each job ran as its own submitit job (its own processes, log and one pickled result), whose handler was called
    # once the checkpoint was written: it took the job for preempted and requeued it.
    logs = sorted((sweep / ".submitit").glob("*/*_log.err"))
    assert len(logs) == 2 and all(log.read_text().count("Caught signal SIGUSR2") == 1 for log in logs)
    assert len(list((sweep / ".submitit").glob("*/*_result.pkl"))) == 2

    # The interrupted seed-0 job ended exactly as an uninterrupted run of the same command.
    straight = tmp_path / "straight"
    cli(monkeypatch, *TINY, "seed=0", "trainer.epochs=2", f"hydra.run.dir={straight}")
    ours, theirs = load_checkpoint(sweep / "seed=0" / "checkpoints" / "last.pt"), load_checkpoint(
        straight / "checkpoints" / "last.pt")
    for name, tensor in theirs["ppo"]["policy"].items():
        assert torch.equal(ours["ppo"]["policy"][name], tensor), name
    assert torch.equal(ours["ppo"]["generator"], theirs["ppo"]["generator"])
    np.testing.assert_array_equal(read_record(straight / "records" / "epoch_000001.npz").actions, a.actions)


def test_slurm_dry_run_prints_the_sbatch_file_and_submits_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip(
        "hydra_plugins.hydra_submitit_launcher", reason="the submitit launcher is the 'cluster' extra (also in 'dev')"
    )
    monkeypatch.chdir(tmp_path)
    cli(monkeypatch, "-m", "hydra/launcher=submitit_slurm", "seed=0,1,2,3,4", "experiment=paper_locomotion",
        "hydra.launcher.partition=gpu", "hydra.launcher.gpus_per_node=2", "hydra.launcher.tasks_per_node=2",
        "hydra.launcher.timeout_min=600", "hydra.launcher.mem_gb=32", "trainer.dry_run=true")
    out = capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []  # no sweep directory, nothing submitted
    for line in ("#SBATCH --array=0-4", "#SBATCH --partition=gpu", "#SBATCH --gpus-per-node=2",
                 "#SBATCH --ntasks-per-node=2", "#SBATCH --time=600", "#SBATCH --mem=32GB", "srun",
                 # requeues: SIGUSR2 120 s before the limit, requeueable (node failure, preemption), logs appended
                 "#SBATCH --signal=USR2@120", "#SBATCH --requeue", "#SBATCH --open-mode=append"):
        assert line in out, line
    assert sum(line.startswith("job ") for line in out.splitlines()) == 5 and "seed 4: 2 rank(s)" in out
    # paper_locomotion: 128 envs over 2 ranks, 64 each; the global minibatch of 128 -> about 64 samples per rank.
    assert "[0, 64)" in out and "[64, 128)" in out and "64.0" in out


def test_torchrun_dry_run_prints_the_split_and_the_command(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("WORLD_SIZE", "3")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "3")
    monkeypatch.setenv("RANK", "0")
    cli(monkeypatch, "env.num_envs=10", "trainer.dry_run=true")
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.strip().startswith(("0 ", "1 ", "2 "))]
    # 10 envs over 3 ranks: 4 + 3 + 3, contiguous; the 256-sample minibatch (of 300) splits 102.4 / 76.8 / 76.8.
    assert [r[2:4] for r in rows] == [["[0,", "4)"], ["[4,", "7)"], ["[7,", "10)"]]
    assert [r[-1] for r in rows] == ["102.4", "76.8", "76.8"]
    assert "torchrun --nnodes=1 --nproc_per_node=3 -m freeform.train env.num_envs=10" in out
    assert "trainer.dry_run" not in out.split("launch:")[1]


def test_dry_run_refuses_more_ranks_than_environments() -> None:
    cfg = TrainConfig()
    cfg.env.num_envs = 2
    with pytest.raises(ValueError, match=r"env\.num_envs \(2\) must be >= the number of ranks \(3\)"):
        describe_split(cfg, 3)


def test_dry_run_flag_in_python_builds_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = TrainConfig()
    cfg.trainer.dry_run = True
    result = train_mod.train(cfg, tmp_path / "run")
    assert result.epochs == 0 and not (tmp_path / "run").exists()
    assert "1 rank(s)" in capsys.readouterr().out


def test_a_job_is_named_by_what_it_trains_not_by_how_it_is_executed(monkeypatch) -> None:
    """Hydra's job subdirectory: the swept keys when there are any; without a sweep every override except the
    experiment and the execution keys (threads, device, progress, print interval), so that a job continued with
    more threads is found in the same directory."""
    from freeform.run.cli import SWEPT_KEYS_ENV, _resolver_sweep_subdir

    task = ["experiment=tiny", "trainer.threads=2", "trainer.device=cpu", "seed=3", "trainer.print_every=5",
            "trainer.epochs=7"]
    monkeypatch.setenv(SWEPT_KEYS_ENV, "")
    assert _resolver_sweep_subdir(task, ["experiment"]) == "seed=3,trainer.epochs=7"
    monkeypatch.setenv(SWEPT_KEYS_ENV, "trainer.threads")
    assert _resolver_sweep_subdir(task, ["experiment"]) == "trainer.threads=2"  # (swept, it names the job)
