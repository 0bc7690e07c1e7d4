"""Design records: the file round trip, and cutting rollouts into episodes (also across rollouts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from freeform.records import (
    EpisodeCollector,
    EpochRecord,
    iter_records,
    list_records,
    read_record,
    record_epoch,
    record_path,
    write_record,
)


def _record(epoch: int, e: int = 5, t: int = 4, rho: int = 6, a: int = 5) -> EpochRecord:
    rng = np.random.default_rng(epoch)
    return EpochRecord(
        epoch=epoch,
        global_step=(epoch + 1) * e * t,
        actions=rng.normal(size=(e, t, a)).astype(np.float32),
        final_grids=rng.integers(0, 2, size=(e, rho, rho, rho), dtype=np.uint8),
        rewards=rng.integers(0, 50, size=e).astype(np.float32),
        values=rng.normal(size=(e, t)).astype(np.float32),
        metrics={"volume": rng.integers(0, 50, size=e).astype(np.float32), "surface_ratio": rng.random(e).astype(np.float32)},
    )


def test_round_trip_keeps_values_and_dtypes(tmp_path: Path) -> None:
    rec = _record(3)
    path = write_record(tmp_path, rec)
    assert path == record_path(tmp_path, 3) == tmp_path / "records" / "epoch_000003.npz"
    back = read_record(path)
    assert (back.epoch, back.global_step, back.num_episodes) == (3, rec.global_step, 5)
    assert back.final_grids.dtype == np.uint8 and back.actions.dtype == np.float32
    for name in ("actions", "final_grids", "rewards", "values"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
    assert back.metrics.keys() == rec.metrics.keys()
    np.testing.assert_array_equal(back.metrics["volume"], rec.metrics["volume"])


def test_grids_are_stored_compressed(tmp_path: Path) -> None:
    rec = _record(0, e=64, rho=16)
    rec.final_grids[:] = 0
    rec.final_grids[:, 4:8, 4:8, 4:8] = 1
    size = write_record(tmp_path, rec).stat().st_size
    assert size < rec.final_grids.nbytes / 20  # 262 kB of uint8 grids shrink to a few kB


def test_listing_orders_by_epoch(tmp_path: Path) -> None:
    for epoch in (10, 2, 0, 1):
        write_record(tmp_path, _record(epoch))
    (tmp_path / "records" / "notes.txt").write_text("ignored")
    assert [p.name for p in list_records(tmp_path)] == [f"epoch_{e:06d}.npz" for e in (0, 1, 2, 10)]
    assert [r.epoch for r in iter_records(tmp_path)] == [0, 1, 2, 10]
    assert list_records(tmp_path / "nothing") == []


def test_record_epoch_inverts_record_path() -> None:
    for epoch in (0, 7, 123456, 1234567):  # past six digits the name just grows
        assert record_epoch(record_path("run", epoch)) == epoch
    for name in ("epoch_12.npz.tmp", "notes.txt", "epoch_.npz", "epoch_-1.npz"):
        with pytest.raises(ValueError, match="not a record file"):
            record_epoch(Path("run/records") / name)


def test_bad_shapes_and_files_raise(tmp_path: Path) -> None:
    rec = _record(0)
    with pytest.raises(ValueError, match="values"):
        EpochRecord(0, 0, rec.actions, rec.final_grids, rec.rewards, rec.values[:, :2])
    with pytest.raises(ValueError, match="final_grids"):
        EpochRecord(0, 0, rec.actions, rec.final_grids[:2], rec.rewards, rec.values)
    with pytest.raises(ValueError, match="metrics"):
        EpochRecord(0, 0, rec.actions, rec.final_grids, rec.rewards, rec.values, {"volume": np.zeros(2)})
    broken = tmp_path / "epoch_000000.npz"
    broken.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="epoch_000000.npz"):
        read_record(broken)


def _rollout(t: int, n: int, done_rows: list[int], start: float) -> dict[str, torch.Tensor]:
    """Actions numbered so that every (step, env) is identifiable: action[s, i, :] = start + 10·s + i."""
    steps = torch.arange(t, dtype=torch.float32)[:, None]
    envs = torch.arange(n, dtype=torch.float32)[None, :]
    ident = start + 10 * steps + envs  # [T, N]
    dones = torch.zeros(t, n, dtype=torch.bool)
    dones[done_rows] = True
    return {
        "actions": ident[..., None].repeat(1, 1, 3),
        "values": -ident,
        "episode_returns": torch.where(dones, ident, torch.zeros(())),  # a sparse terminal reward's returns
        "dones": dones,
    }


def _infos(n: int, count: int, rho: int = 4) -> list[dict]:
    return [
        {"final_grids": torch.full((n, rho, rho, rho), k, dtype=torch.uint8), "metrics": {"volume": torch.arange(n) + k}}
        for k in range(count)
    ]


def test_collector_aligned_rollout() -> None:
    """rollout_steps == T: one episode per environment, the rollout transposed to [E, T, A]."""
    n, t = 3, 4
    roll = _rollout(t, n, [3], start=0.0)
    out = EpisodeCollector().collect(roll, _infos(n, 1))
    assert out is not None
    assert out["actions"].shape == (n, t, 3) and out["values"].shape == (n, t)
    np.testing.assert_array_equal(out["actions"][:, :, 0], roll["actions"][:, :, 0].T.numpy())
    np.testing.assert_array_equal(out["values"], -roll["actions"][:, :, 0].T.numpy())
    np.testing.assert_array_equal(out["rewards"], [30.0, 31.0, 32.0])  # ident at s = 3
    assert out["final_grids"].dtype == np.uint8 and out["final_grids"].shape == (n, 4, 4, 4)
    np.testing.assert_array_equal(out["metrics"]["volume"], [0, 1, 2])


def test_collector_episode_spanning_rollouts() -> None:
    """T = 4, rollouts of 6 steps: episodes end at rollout-1 step 3 and rollout-2 step 1 (2 carried + 2 new)."""
    n = 2
    col = EpisodeCollector()
    r1 = _rollout(6, n, [3], start=0.0)
    out1 = col.collect(r1, _infos(n, 1))
    assert out1 is not None and out1["actions"].shape == (n, 4, 3)
    # The carried tail survives a state_dict round trip (that is what a resumed run relies on).
    fresh = EpisodeCollector()
    fresh.load_state_dict(col.state_dict())
    r2 = _rollout(6, n, [1, 5], start=100.0)
    out2 = fresh.collect(r2, _infos(n, 2))
    assert out2 is not None and out2["actions"].shape == (2 * n, 4, 3)
    # Episode 1 = steps 4, 5 of rollout 1, then steps 0, 1 of rollout 2.
    np.testing.assert_array_equal(out2["actions"][0, :, 0], [40.0, 50.0, 100.0, 110.0])
    np.testing.assert_array_equal(out2["actions"][n + 1, :, 0], [121.0, 131.0, 141.0, 151.0])
    np.testing.assert_array_equal(out2["rewards"], [110.0, 111.0, 150.0, 151.0])
    np.testing.assert_array_equal(out2["metrics"]["volume"], [0, 1, 1, 2])
    assert fresh.state_dict() == {}  # nothing left over


def test_collector_no_finish_and_lockstep_check() -> None:
    col = EpisodeCollector()
    assert col.collect(_rollout(3, 2, [], 0.0), []) is None
    bad = _rollout(3, 2, [], 0.0)
    bad["dones"][1, 0] = True
    with pytest.raises(ValueError, match="lock-step"):
        EpisodeCollector().collect(bad, _infos(2, 1))
    with pytest.raises(ValueError, match="episode_infos"):
        EpisodeCollector().collect(_rollout(3, 2, [2], 0.0), [])
