"""Checkpoints: round trip, atomicity (a crash or a kill mid-write leaves the last good file), clear errors, RNG."""

from __future__ import annotations

import errno
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from freeform import checkpoint as ck
from freeform.checkpoint import (
    CheckpointError,
    capture_rng_state,
    load_checkpoint,
    resolve_checkpoint,
    restore_rng_state,
    run_dir_of,
    save_checkpoint,
)


def _state(i: int) -> dict:
    return {"i": i, "weights": {"w": torch.full((3, 4), float(i))}, "name": "x", "none": None, "nested": [1, 2.5]}


BITS = {1: torch.uint8, 2: torch.int16, 4: torch.int32, 8: torch.int64}


def _mostly_zero(dtype: torch.dtype) -> torch.Tensor:
    """[128, 17, 8, 8, 8] (1.1 M elements), non-zero in 10 % of the cells, with −0.0s (a negative value times a
    zero mask), NaN, a subnormal and infinity where the dtype has them."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(128, 17, 8, 8, 8, generator=g, dtype=torch.float64) * 3
    x = x * (torch.rand(128, 1, 8, 8, 8, generator=g, dtype=torch.float64) < 0.1)
    if not dtype.is_floating_point:
        return (x > 1).to(dtype) if dtype == torch.bool else x.round().to(dtype)
    x = x.to(dtype)
    x.view(-1)[:4] = torch.tensor([-0.0, float("nan"), torch.finfo(dtype).smallest_normal / 4, float("inf")],
                                  dtype=torch.float64).to(dtype)
    assert torch.signbit(x[x == 0]).float().mean() > 0.3
    return x


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16, torch.int64,
                                   torch.int32, torch.int16, torch.int8, torch.uint8, torch.bool])
def test_mostly_zero_tensors_are_written_packed_and_read_back_bit_for_bit(tmp_path: Path, dtype) -> None:
    """A distillation's dataset is observations zero outside the bodies: written as its non-zero elements and a bit
    mask, it takes a fraction of its bytes on disk and reads back with every bit as it was (−0.0, NaN, a
    subnormal; a transposed view too); dense or small tensors, and containers with nothing packed, are written as
    they are."""
    from collections import OrderedDict

    x = _mostly_zero(dtype)
    g = torch.Generator().manual_seed(1)
    weights = OrderedDict(w=torch.zeros(10))
    state = {"dataset": {"obs": x, "turned": x.transpose(0, 1)}, "dense": torch.randn(1 << 20, generator=g),
             "weights": weights}
    path = save_checkpoint(tmp_path / "last.pt", state)
    raw = torch.load(path, weights_only=True)
    assert ck.PACKED in raw["dataset"]["obs"] and ck.PACKED in raw["dataset"]["turned"]
    assert isinstance(raw["dense"], torch.Tensor) and isinstance(raw["weights"], OrderedDict)
    assert path.stat().st_size < 0.6 * 2 * x.numel() * x.element_size() + 1.01 * (1 << 20) * 4
    back = load_checkpoint(path)
    for key in ("obs", "turned"):
        y, want = back["dataset"][key], state["dataset"][key]
        assert y.dtype == dtype and y.shape == want.shape, key
        bits = BITS[x.element_size()]
        assert torch.equal(y.contiguous().view(bits), want.contiguous().view(bits)), key
    assert torch.equal(back["dense"], state["dense"]) and isinstance(back["weights"], OrderedDict)
    once = ck.pack_sparse(state)  # (a run packs once for last.pt and epoch_<e>.pt: packing twice changes nothing)
    assert ck.pack_sparse(once)["dataset"]["obs"] is once["dataset"]["obs"]


def test_round_trip(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "a" / "last.pt", _state(3))
    state = load_checkpoint(path)
    assert state["i"] == 3 and state["name"] == "x" and state["none"] is None and state["nested"] == [1, 2.5]
    assert torch.equal(state["weights"]["w"], torch.full((3, 4), 3.0))
    assert state["format"] == ck.FORMAT and state["version"] == ck.VERSION


def test_failed_write_keeps_the_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = save_checkpoint(tmp_path / "last.pt", _state(1))

    def crash(obj: object, f: object) -> None:  # dies half-way through writing
        f.write(b"PK\x03\x04 half a zip")  # type: ignore[attr-defined]
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", crash)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, _state(2))
    assert load_checkpoint(path)["i"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]  # no temporary file left behind


def test_a_write_the_file_system_refuses_raises_its_oserror_and_keeps_the_previous_file(tmp_path: Path) -> None:
    """A file-size limit (like a quota or a full disk, and enforced for root too) hit half-way through torch.save:
    torch itself would report ``RuntimeError: ... unexpected pos``; save_checkpoint raises the OSError (EFBIG)."""
    resource = pytest.importorskip("resource")
    path = save_checkpoint(tmp_path / "last.pt", _state(1))
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # else the kernel's SIGXFSZ ends the process
    resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, hard))
    try:
        with pytest.raises(OSError) as info:
            save_checkpoint(path, {"big": torch.zeros(100_000), **_state(2)})
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert info.value.errno == errno.EFBIG
    assert load_checkpoint(path)["i"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]  # no temporary file left behind


def test_killed_writer_leaves_a_readable_checkpoint(tmp_path: Path) -> None:
    """SIGKILL a process that rewrites last.pt in a loop (several MB each): the file is always complete."""
    path = tmp_path / "last.pt"
    script = textwrap.dedent(
        f"""
        import torch
        from freeform.checkpoint import save_checkpoint
        i = 0
        while True:
            save_checkpoint({str(path)!r}, {{"i": i, "big": torch.full((1_000_000,), float(i))}})
            i += 1
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        deadline = time.monotonic() + 60
        while not path.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3 + random.random() * 0.3)  # land somewhere inside a later write
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    state = load_checkpoint(path)
    assert torch.equal(state["big"], torch.full((1_000_000,), float(state["i"])))


def test_truncated_checkpoint_names_the_file_and_the_others(tmp_path: Path) -> None:
    good = save_checkpoint(tmp_path / "epoch_000010.pt", _state(10))
    bad = tmp_path / "last.pt"
    data = good.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"last\.pt is unreadable") as info:
        load_checkpoint(bad)
    assert str(bad) in str(info.value) and "epoch_000010.pt" in str(info.value)
    assert good.read_bytes() == data  # loading wrote nothing


def test_garbage_and_foreign_files_are_rejected(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="garbage.pt"):
        load_checkpoint(garbage)
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": torch.zeros(2)}, foreign)
    with pytest.raises(CheckpointError, match="not a freeform checkpoint"):
        load_checkpoint(foreign)
    newer = tmp_path / "newer.pt"
    torch.save({"format": ck.FORMAT, "version": ck.VERSION + 1}, newer)
    with pytest.raises(CheckpointError, match="version"):
        load_checkpoint(newer)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")


def test_pickled_code_is_not_executed(tmp_path: Path) -> None:
    """weights_only loading: a checkpoint cannot carry arbitrary objects."""

    class Evil:
        def __reduce__(self) -> tuple:
            return (os.system, ("echo pwned",))

    path = tmp_path / "evil.pt"
    torch.save({"format": ck.FORMAT, "version": ck.VERSION, "x": Evil()}, path)
    with pytest.raises(CheckpointError, match="evil.pt"):
        load_checkpoint(path)


def _draws() -> tuple:
    return random.random(), random.gauss(0, 1), np.random.rand(3).tolist(), np.random.randn(), torch.rand(3).tolist()


def test_rng_capture_restore_survives_a_file(tmp_path: Path) -> None:
    random.seed(1)
    np.random.seed(2)
    torch.manual_seed(3)
    random.gauss(0, 1)  # leave a cached gaussian in python's state
    np.random.randn()
    save_checkpoint(tmp_path / "rng.pt", {"rng": capture_rng_state()})
    expected = _draws()
    _draws()  # move every generator on
    restore_rng_state(load_checkpoint(tmp_path / "rng.pt")["rng"])
    assert _draws() == expected


def test_resolve_and_run_dir(tmp_path: Path) -> None:
    run = tmp_path / "run"
    save_checkpoint(run / "checkpoints" / "last.pt", _state(0))
    assert resolve_checkpoint(run) == run / "checkpoints" / "last.pt"
    assert resolve_checkpoint(run / "checkpoints") == run / "checkpoints" / "last.pt"
    assert resolve_checkpoint(run / "checkpoints" / "x.pt") == run / "checkpoints" / "x.pt"
    assert run_dir_of(run / "checkpoints" / "epoch_000010.pt") == run
    assert run_dir_of(run) == run
    assert run_dir_of(tmp_path / "loose.pt") == tmp_path


# ---------------------------------------------------------------------------------------------------------------
# One path for PPO files and run checkpoints: what a file names is built only if allowed; old files still load.
# ---------------------------------------------------------------------------------------------------------------


class _FlatEnv:
    """Four envs whose observation never changes (enough to build, save and load a PPO)."""

    num_envs, observation_shape, action_dim, device = 4, (3,), 2, torch.device("cpu")

    def reset(self, seed: int | None = None) -> torch.Tensor:
        return torch.ones(4, 3)

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        return torch.ones(4, 3), torch.zeros(4), torch.zeros(4, dtype=torch.bool), {}


class MyPolicy(torch.nn.Module):
    """A user's own policy class: a checkpoint may name it, but loading builds it only when the caller allows it."""

    built = 0

    def __init__(self, scale: float = 1.0) -> None:
        super().__init__()
        MyPolicy.built += 1
        self.init_kwargs = {"scale": scale}
        self.body = torch.nn.Linear(3, 5)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.body(obs)
        return out[:, :2], out[:, 2:4], out[:, 4]


def test_ppo_files_and_run_checkpoints_share_one_writer_and_a_class_is_built_only_if_allowed(tmp_path: Path) -> None:
    from freeform.agents import PPO, PPOConfig

    ppo = PPO(_FlatEnv(), MyPolicy(scale=2.0), PPOConfig(rollout_steps=2, sgd_minibatch_size=4, num_sgd_iter=1))
    ppo.train_epoch()
    ppo.save(tmp_path / "mine.pt")
    raw = load_checkpoint(tmp_path / "mine.pt")  # the one loader reads it: weights_only, format and version stamped
    assert raw["policy_class"].endswith(":MyPolicy") and raw["version"] == ck.VERSION
    built = MyPolicy.built
    with pytest.raises(CheckpointError, match=r"mine\.pt: its policy class .*MyPolicy.* policy_classes="):
        PPO.load(tmp_path / "mine.pt", _FlatEnv())
    assert MyPolicy.built == built  # nothing named by the file was built
    loaded = PPO.load(tmp_path / "mine.pt", _FlatEnv(), policy_classes=[MyPolicy])
    assert loaded.policy.init_kwargs == {"scale": 2.0} and loaded.epoch == 1
    for name, tensor in ppo.policy.state_dict().items():
        assert torch.equal(loaded.policy.state_dict()[name], tensor)


def test_version_2_run_checkpoints_resume_exactly(tmp_path: Path) -> None:
    """A run checkpoint of the previous format (the episode collector's carry at its top level, as main wrote it
    before the learner owned it) resumes exactly: rollouts of 7 steps cut episodes of T = 5, so the carry matters,
    and the resumed run's second record equals the uninterrupted run's. Version 1 (never released) is refused."""
    from helpers import tiny

    from freeform.config import compose
    from freeform.records import read_record
    from freeform.run.trainer import train

    cfg = compose(*tiny("trainer.epochs=2", "agent.rollout_steps=7", "trainer.checkpoint_every=0"))
    train(cfg, tmp_path / "straight")
    cfg.trainer.epochs = 1
    train(cfg, tmp_path / "split")
    last = tmp_path / "split" / "checkpoints" / "last.pt"
    state = torch.load(last, weights_only=True)
    carry = state["ppo"].pop("episode_carry")
    assert carry and all(len(v) == 2 for v in carry.values())  # 7 steps = one episode of 5 + 2 carried
    torch.save({**state, "version": 2, "collector": carry}, last)
    cfg.trainer.epochs, cfg.trainer.resume = 2, str(tmp_path / "split")
    train(cfg, tmp_path / "split")
    a, b = (read_record(tmp_path / run / "records" / "epoch_000001.npz") for run in ("straight", "split"))
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.rewards, b.rewards)
    torch.save({**state, "version": 1}, tmp_path / "v1.pt")
    with pytest.raises(CheckpointError, match="version 1; this freeform reads 2 to"):
        load_checkpoint(tmp_path / "v1.pt")


def test_run_files_get_the_umask_permissions_not_mkstemps_0600(tmp_path: Path) -> None:
    """Group members of a shared cluster read each other's runs: the atomic writer's temporary file (0600) must not
    leave checkpoints and records private."""
    from freeform.files import write_atomically

    old = os.umask(0o022)
    try:
        path = save_checkpoint(tmp_path / "last.pt", _state(1))
        other = write_atomically(tmp_path / "info.json", lambda f: f.write(b"{}"))
    finally:
        os.umask(old)
    assert (path.stat().st_mode & 0o777) == (other.stat().st_mode & 0o777) == 0o644
    assert other.read_bytes() == b"{}" and sorted(p.name for p in tmp_path.iterdir()) == ["info.json", "last.pt"]


def test_a_numbered_checkpoint_is_a_copy_of_last_pt_that_keeps_its_epoch(tmp_path: Path) -> None:
    """The run directory writes last.pt once and copies its bytes to the numbered name; the numbered file keeps that
    epoch's state when last.pt is written again, or overwritten in place by a user's ``cp`` rollback."""
    import shutil

    from freeform.run.rundir import RunDir

    run = RunDir(tmp_path, writer=True)
    run.save_checkpoint(_state(2), 2, numbered=True)
    directory = tmp_path / ck.CHECKPOINT_DIR
    last, numbered = directory / ck.LAST, directory / ck.numbered_name(2)
    assert numbered.read_bytes() == last.read_bytes() and not os.path.samefile(last, numbered)
    run.save_checkpoint(_state(3), 3, numbered=False)
    assert load_checkpoint(numbered)["i"] == 2 and load_checkpoint(last)["i"] == 3
    save_checkpoint(tmp_path / "other.pt", _state(9))
    shutil.copyfile(tmp_path / "other.pt", last)  # (in place: the file's inode kept)
    assert load_checkpoint(numbered)["i"] == 2
    assert sorted(p.name for p in directory.iterdir()) == sorted([ck.LAST, ck.numbered_name(2)])  # no temporary left
    assert run.failure is None and run.saved_epoch == 3
    run.save_checkpoint(_state(4), 4, numbered=True, last=False)  # (a numbered file alone is serialised as before)
    assert load_checkpoint(directory / ck.numbered_name(4))["i"] == 4 and load_checkpoint(last)["i"] == 9
