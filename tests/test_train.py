"""The training application end to end, at tiny sizes (ρ = 6, 4 environments, T = 5).

Through the CLI (``freeform.train.main`` with ``sys.argv``, as the console script calls it): a run writes events,
checkpoints and design records; a resumed run continues the same TensorBoard curves (read back with
EventAccumulator) with no gap and no duplicate; bad input fails with a message naming the key or file; a multirun
writes one directory per seed; and 2 epochs equal 1 epoch + resume 1, bit for bit.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import run_cli as cli  # tests/helpers.py
from helpers import scalars, straight_and_resumed, tiny
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from freeform import train as train_mod
from freeform.checkpoint import load_checkpoint
from freeform.records import iter_records, read_record
from freeform.run import rundir as rundir_mod

TINY = tiny()
STEPS_PER_EPOCH = 4 * 5


@pytest.fixture(scope="module")
def base_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-epoch tiny run (shared by the tests that only read it)."""
    run = tmp_path_factory.mktemp("base") / "run"
    with pytest.MonkeyPatch.context() as mp:
        cli(mp, *TINY, "trainer.epochs=3", "trainer.render_every=2", f"hydra.run.dir={run}")
    return run


def test_run_writes_events_checkpoints_records(base_run: Path) -> None:
    tags = scalars(base_run)
    steps = [STEPS_PER_EPOCH * (e + 1) for e in range(3)]
    for tag in ("charts/episode_reward_mean", "charts/episode_reward_max", "losses/policy_loss",
                "losses/value_loss", "losses/approx_kl", "losses/kl_coeff", "losses/entropy",
                "losses/explained_variance", "perf/samples_per_second", "perf/time_update", "perf/time_logging"):
        assert [s for s, _ in tags[tag]] == steps, tag
    for metric in ("volume", "surface_ratio", "passive_ratio", "lcc_ratio", "substructures", "symmetry",
                   "compressibility"):
        assert [s for s, _ in tags[f"body/{metric}"]] == steps, metric
    acc = EventAccumulator(str(base_run), size_guidance={"tensors": 0, "images": 0})
    acc.Reload()
    assert "config/text_summary" in acc.Tags()["tensors"]
    # The render hook ran at epochs 0 and 2 (trainer.render_every=2).
    assert [e.step for e in acc.Images("bodies/best")] == [steps[0], steps[2]]

    # Records: one per epoch, 4 episodes each; their rewards are the TensorBoard mean, computed independently.
    records = list(iter_records(base_run))
    assert [r.epoch for r in records] == [0, 1, 2]
    for rec, (step, mean) in zip(records, tags["charts/episode_reward_mean"], strict=True):
        assert rec.global_step == step
        assert rec.actions.shape == (4, 5, 3 + 2) and rec.values.shape == (4, 5)
        assert rec.final_grids.shape == (4, 6, 6, 6) and rec.final_grids.dtype == np.uint8
        assert rec.rewards.mean() == pytest.approx(mean)
        # Volume task: the reward is the body's voxel count, and a body is never larger than the grid's voxels.
        np.testing.assert_array_equal(rec.rewards, rec.metrics["volume"])
        assert np.all(rec.rewards <= (rec.final_grids > 0).sum(axis=(1, 2, 3)))

    ckpt = load_checkpoint(base_run / "checkpoints" / "last.pt")
    assert (ckpt["epoch"], ckpt["global_step"]) == (3, 3 * STEPS_PER_EPOCH)
    assert ckpt["config"]["env"]["resolution"] == 6
    assert {"ppo", "rng", "policy_kwargs"} <= ckpt.keys() and "episode_carry" in ckpt["ppo"]  # (format 3)
    assert sorted(p.name for p in (base_run / "checkpoints").iterdir()) == [
        "epoch_000000.pt", "epoch_000001.pt", "epoch_000002.pt", "epoch_000003.pt", "last.pt"]
    info = json.loads((base_run / "run_info.json").read_text())
    assert info["torch"] == torch.__version__ and info["device"] == "cpu" and info["seed"] == 0
    assert {"freeform", "taichi", "git_commit", "start_time"} <= info.keys()


def test_resume_after_a_kill_continues_the_curves_exactly(
    base_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run killed after logging epoch 2 but before checkpointing it: resuming drops its epoch-2 events, redoes
    epoch 2 and goes on; the curves and records equal the uninterrupted run's (``base_run``)."""
    run = tmp_path / "run"
    cli(monkeypatch, *TINY, "trainer.epochs=2", f"hydra.run.dir={run}")
    shutil.copy(run / "checkpoints" / "epoch_000001.pt", run / "checkpoints" / "last.pt")  # the "kill"
    cli(monkeypatch, f"trainer.resume={run}", "trainer.epochs=3")

    got, want = scalars(run), scalars(base_run)
    for tag in ("charts/episode_reward_mean", "losses/policy_loss", "losses/value_loss", "body/volume"):
        assert got[tag] == want[tag], tag  # same steps, no duplicate, no gap, same values
    for a, b in zip(iter_records(run), iter_records(base_run), strict=True):
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.final_grids, b.final_grids)
    assert any(p.name.startswith("resume_") for p in (run / ".hydra").iterdir())  # the original config is kept
    info = json.loads((run / "run_info.json").read_text())
    assert [r["epoch"] for r in info["resumes"]] == [1]


def test_two_epochs_equal_one_plus_resume_one_bit_for_bit(tmp_path: Path) -> None:
    from freeform.config import compose

    straight_and_resumed(compose(*TINY, "seed=5"), tmp_path, epochs=2)

    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")
    b = load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")
    for name, tensor in a["ppo"]["policy"].items():
        assert torch.equal(tensor, b["ppo"]["policy"][name]), name
    for sa, sb in zip(a["ppo"]["optimizer"]["state"].values(), b["ppo"]["optimizer"]["state"].values(), strict=True):
        assert all(torch.equal(sa[k], sb[k]) for k in ("exp_avg", "exp_avg_sq"))
    assert a["ppo"]["kl_coeff"] == b["ppo"]["kl_coeff"]
    assert torch.equal(a["ppo"]["generator"], b["ppo"]["generator"])
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    ra, rb = read_record(tmp_path / "straight" / "records" / "epoch_000001.npz"), read_record(
        tmp_path / "split" / "records" / "epoch_000001.npz")
    np.testing.assert_array_equal(ra.actions, rb.actions)
    np.testing.assert_array_equal(ra.values, rb.values)


def test_bad_override_fails_with_a_clear_message(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli(monkeypatch, "agent.lrr=1", f"hydra.run.dir={tmp_path / 'a'}")
    assert "agent.lrr" in capsys.readouterr().err
    with pytest.raises(SystemExit, match=r"env\.resolution must be an even integer"):
        cli(monkeypatch, "env.resolution=7", f"hydra.run.dir={tmp_path / 'b'}")
    with pytest.raises(SystemExit, match=r"task\.name must be one of \[.*'locomotion'.*'volume'\], got 'swim'"):
        cli(monkeypatch, *TINY, "task.name=swim", f"hydra.run.dir={tmp_path / 'c'}")


def test_resume_errors_name_the_file_and_lose_nothing(base_run: Path, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    run = tmp_path / "run"
    shutil.copytree(base_run, run)
    last = run / "checkpoints" / "last.pt"
    last.write_bytes(last.read_bytes()[:1000])  # truncated by a crash of the disk, say
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and ".hydra" not in p.parts}
    with pytest.raises(SystemExit, match=r"last\.pt is unreadable.*epoch_000003\.pt"):
        cli(monkeypatch, f"trainer.resume={run}", "trainer.epochs=4")
    after = {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and ".hydra" not in p.parts and p.suffix != ".log"}
    assert after == {p: v for p, v in before.items() if p.suffix != ".log"}
    # Resuming from a good numbered checkpoint while changing what the run trains is refused.
    with pytest.raises(SystemExit, match=r"agent\.lr: cannot change"):
        cli(monkeypatch, f"trainer.resume={run / 'checkpoints' / 'epoch_000003.pt'}", "agent.lr=0.5")


def test_multirun_writes_one_directory_per_seed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sweep = tmp_path / "sweep"
    cli(monkeypatch, "-m", *TINY, "trainer.epochs=1", "trainer.checkpoint_every=0", "seed=0,1",
        f"hydra.sweep.dir={sweep}")
    runs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert runs == ["seed=0", "seed=1"]
    seeds = [json.loads((sweep / r / "run_info.json").read_text())["seed"] for r in runs]
    assert seeds == [0, 1]
    a, b = (read_record(sweep / r / "records" / "epoch_000000.npz") for r in runs)
    assert not np.array_equal(a.actions, b.actions)  # different seeds, different designs
    assert sorted(p.name for p in (sweep / "seed=0" / "checkpoints").iterdir()) == ["last.pt"]


def test_console_script_is_installed() -> None:
    script = Path(sys.executable).parent / "freeform-train"
    out = subprocess.run([str(script), "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    for group in ("task:", "env:", "agent:", "trainer:", "experiment:", "paper_volume", "volume_cpu"):
        assert group in out.stdout, group


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message given where no CUDA device exists")
def test_gpu_preset_without_cuda_stops_at_once_naming_the_cpu_override(tmp_path: Path) -> None:
    from freeform.config import compose

    cfg = compose("experiment=paper_locomotion")
    assert cfg.trainer.device == "cuda"
    with pytest.raises(ValueError, match=r"experiment=paper_locomotion is meant for a GPU.*add trainer\.device=cpu agent\.cuda_graph=false"):
        train_mod.train(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()  # nothing was written


def test_records_hold_raw_returns_with_reward_norm(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """agent.reward_norm scales what PPO learns from, never what the robots scored: two runs that differ only in
    reward_norm collect the same first epoch (the rewards enter no decision before the first update), so their
    first records hold the same returns — the volume task's, each body's voxel count — and TensorBoard's mean."""
    runs = {flag: tmp_path / f"norm_{flag}" for flag in ("false", "true")}
    for flag, run in runs.items():
        cli(monkeypatch, *TINY, "trainer.epochs=1", f"agent.reward_norm={flag}", f"hydra.run.dir={run}")
    plain, normed = (read_record(run / "records" / "epoch_000000.npz") for run in runs.values())
    np.testing.assert_array_equal(normed.final_grids, plain.final_grids)
    np.testing.assert_array_equal(normed.rewards, plain.rewards)
    np.testing.assert_array_equal(normed.rewards, normed.metrics["volume"])
    assert plain.rewards.max() > 10  # (normalised and clipped returns would be small numbers)
    for run in runs.values():
        assert scalars(run)["charts/episode_reward_mean"][0][1] == pytest.approx(float(plain.rewards.mean()))


def test_dense_rewards_from_the_command_line_keep_the_terminal_return(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """env.dense_every=k wraps the design env in DenseDesignReward: the episode's rewards (what PPO learns from)
    differ from the sparse run's, but they sum to the same terminal reward, so the records and the logged return —
    and the designs, which do not depend on the rewards in the first epoch — equal the sparse run's."""
    sparse, dense = tmp_path / "sparse", tmp_path / "dense"
    cli(monkeypatch, *TINY, "trainer.epochs=1", f"hydra.run.dir={sparse}")
    cli(monkeypatch, *TINY, "trainer.epochs=1", "env.dense_every=2", f"hydra.run.dir={dense}")
    a, b = read_record(sparse / "records" / "epoch_000000.npz"), read_record(dense / "records" / "epoch_000000.npz")
    np.testing.assert_array_equal(a.final_grids, b.final_grids)
    # What the task scored (info["task_reward"]), not the dense rewards' float32 sum: equal to the bit.
    np.testing.assert_array_equal(b.rewards, a.rewards)
    assert a.rewards.max() > 0
    assert scalars(dense)["charts/episode_reward_mean"][0][1] == pytest.approx(float(a.rewards.mean()), rel=1e-6)
    # The dense run's env is the wrapper (its per-environment scoring state is checkpointed); the sparse one is not.
    assert "dense_last" in load_checkpoint(dense / "checkpoints" / "last.pt")["ppo"]["env"]["per_env"]
    assert "dense_last" not in load_checkpoint(sparse / "checkpoints" / "last.pt")["ppo"]["env"]["per_env"]
    with pytest.raises(SystemExit, match=r"env\.dense_every must be an integer in \[0, env\.steps=5\]"):
        cli(monkeypatch, *TINY, "env.dense_every=9", f"hydra.run.dir={tmp_path / 'bad'}")


def test_git_commit_is_the_checkouts_own_never_an_enclosing_repositorys(tmp_path: Path) -> None:
    """A wheel installed in a venv inside another repository is not that repository's source: no commit is
    recorded for it; the checkout this suite runs from records its own HEAD."""
    sha, _ = rundir_mod._git_commit()
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(train_mod.__file__).parent, capture_output=True,
                          text=True)
    assert head.returncode == 0 and sha == head.stdout.strip()
    user_repo = tmp_path / "project"
    installed = user_repo / ".venv" / "lib" / "python3.11" / "site-packages" / "freeform"
    installed.mkdir(parents=True)
    (installed / "__init__.py").write_text("")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], cwd=user_repo, check=True)
    subprocess.run([*git, "add", "-A"], cwd=user_repo, check=True)  # even a committed venv is not freeform's source
    subprocess.run([*git, "commit", "-qm", "x"], cwd=user_repo, check=True)
    assert rundir_mod._git_commit(installed) == (None, None)
