"""Per-epoch design records: every episode's raw actions, final grid, reward, critic values and body metrics.

A run writes ``records/epoch_<e>.npz`` (compressed) for each epoch e = 0, 1, ... — the designs produced by the
policy after e updates, i.e. by the policy stored in ``checkpoints/epoch_<e>.pt`` when that exists. The paper's
analyses read them: the across-seed curves and example bodies (rewards, grids), the critic-accuracy experiment
(grids, rewards, values) and the robustness replay (raw actions). Read them with :func:`read_record` /
:func:`iter_records`; never with ``np.load`` on guessed keys.

Arrays in a record (E = episodes finished in the epoch, T = actions per episode, A = 3 + k):

==================  ==========================  ======================================================
key                 shape / dtype               meaning
==================  ==========================  ======================================================
``actions``         ``[E, T, A] float32``       raw policy samples, before the environment's clip
``final_grids``     ``[E, ρ, ρ, ρ] uint8``      material indices of the grid after the last action
``rewards``         ``[E] float32``             episode return (the terminal reward with the paper's task)
``values``          ``[E, T] float32``          critic's V(s_t), t = 0 … T−1, as computed in the rollout
``metric_<name>``   ``[E] float32``             body metrics (``freeform.body``), e.g. ``metric_volume``
``yaw``             ``[E] int8``                the placement the task scored, quarter turns counterclockwise
                                                seen from above (``task.options.placements``; 0 = as designed;
                                                records without it read as 0)
``epoch``           ``[] int64``                epoch index e
``global_step``     ``[] int64``                environment steps (all environments) after the epoch
==================  ==========================  ======================================================
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freeform.files import write_atomically

RECORDS_DIR = "records"
_METRIC_PREFIX = "metric_"
_NAME = re.compile(r"^epoch_(\d+)\.npz$")


@dataclass
class EpochRecord:
    """The designs of one epoch (shapes in the module docstring)."""

    epoch: int
    global_step: int
    actions: np.ndarray
    final_grids: np.ndarray
    rewards: np.ndarray
    values: np.ndarray
    metrics: dict[str, np.ndarray] = field(default_factory=dict)
    yaw: np.ndarray | None = None
    """``[E]`` quarter turns of each body's scored placement; None = all 0 (as designed)."""

    def __post_init__(self) -> None:
        e = len(self.rewards)
        self.yaw = np.zeros(e, np.int8) if self.yaw is None else np.asarray(self.yaw).astype(np.int8)
        if self.yaw.shape != (e,):
            raise ValueError(f"yaw must be [E={e}], got shape {self.yaw.shape}")
        if self.actions.ndim != 3 or len(self.actions) != e:
            raise ValueError(f"actions must be [E={e}, T, A], got shape {self.actions.shape}")
        if self.final_grids.ndim != 4 or len(self.final_grids) != e:
            raise ValueError(f"final_grids must be [E={e}, ρ, ρ, ρ], got shape {self.final_grids.shape}")
        if self.values.shape != self.actions.shape[:2]:
            raise ValueError(f"values must be [E, T]={self.actions.shape[:2]}, got shape {self.values.shape}")
        for name, m in self.metrics.items():
            if m.shape != (e,):
                raise ValueError(f"metrics[{name!r}] must be [E={e}], got shape {m.shape}")

    @property
    def num_episodes(self) -> int:
        return len(self.rewards)

    def placed_grids(self) -> np.ndarray:
        """``final_grids`` turned to the placement each body was scored at (:func:`placed`)."""
        return placed(self.final_grids, self.yaw)


def placed(grids: np.ndarray, yaw: np.ndarray | None) -> np.ndarray:
    """Grids ``[E, X, Y, Z]`` turned by ``yaw [E]`` quarter turns about the vertical axis (counterclockwise seen from
    above, as the task placed them: ``torch.rot90(..., dims=(1, 2))``); ``yaw`` None or all 0: the grids as they
    are. What renders and exports draw, so a picture shows the robot as it was scored."""
    if yaw is None or not np.any(yaw):
        return grids
    return np.stack([np.rot90(g, int(q), axes=(0, 1)) for g, q in zip(grids, yaw, strict=True)])


def record_path(run_dir: str | os.PathLike[str], epoch: int) -> Path:
    """``<run_dir>/records/epoch_<epoch:06d>.npz``."""
    return Path(run_dir) / RECORDS_DIR / f"epoch_{epoch:06d}.npz"


def record_epoch(path: str | os.PathLike[str]) -> int:
    """The epoch a record file is named for: the inverse of ``record_path`` (``ValueError`` for another name)."""
    match = _NAME.match(Path(path).name)
    if match is None:
        raise ValueError(f"{path} is not a record file (epoch_<epoch>.npz)")
    return int(match.group(1))


def write_record(run_dir: str | os.PathLike[str], record: EpochRecord) -> Path:
    """Write ``record`` compressed and atomically (``freeform.files.write_atomically``); returns its path."""
    path = record_path(run_dir, record.epoch)
    arrays: dict[str, np.ndarray] = {
        "actions": record.actions.astype(np.float32, copy=False),
        "final_grids": record.final_grids.astype(np.uint8, copy=False),
        "rewards": record.rewards.astype(np.float32, copy=False),
        "values": record.values.astype(np.float32, copy=False),
        "epoch": np.asarray(record.epoch, dtype=np.int64),
        "global_step": np.asarray(record.global_step, dtype=np.int64),
        "yaw": np.asarray(record.yaw, dtype=np.int8),
    }
    for name, m in record.metrics.items():
        arrays[_METRIC_PREFIX + name] = m.astype(np.float32, copy=False)
    return write_atomically(path, lambda f: np.savez_compressed(f, **arrays))  # type: ignore[arg-type]


def read_record(path: str | os.PathLike[str]) -> EpochRecord:
    """Read one record file (``ValueError`` naming the file if it is not a complete record)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"design record {path} is unreadable: {type(exc).__name__}: {exc}") from exc
    missing = {"actions", "final_grids", "rewards", "values", "epoch", "global_step"} - arrays.keys()
    if missing:
        raise ValueError(f"design record {path} lacks {sorted(missing)}")
    return EpochRecord(
        epoch=int(arrays["epoch"]),
        global_step=int(arrays["global_step"]),
        actions=arrays["actions"],
        final_grids=arrays["final_grids"],
        rewards=arrays["rewards"],
        values=arrays["values"],
        metrics={k[len(_METRIC_PREFIX) :]: v for k, v in arrays.items() if k.startswith(_METRIC_PREFIX)},
        yaw=arrays.get("yaw"),  # (records written before placements have none: as designed)
    )


def list_records(run_dir: str | os.PathLike[str]) -> list[Path]:
    """The run's record files, ordered by epoch."""
    directory = Path(run_dir) / RECORDS_DIR
    if not directory.is_dir():
        return []
    return sorted((p for p in directory.iterdir() if _NAME.match(p.name)), key=record_epoch)


def iter_records(run_dir: str | os.PathLike[str]) -> Iterator[EpochRecord]:
    """Read the run's records one by one, in epoch order."""
    for path in list_records(run_dir):
        yield read_record(path)


def _field(container: Any, name: str) -> Any:
    return container[name] if isinstance(container, Mapping) else getattr(container, name)


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu").numpy()


class EpisodeCollector:
    """Cuts PPO's rollouts into finished episodes (lock-step environments: every environment ends together).

    An episode may span rollouts (when ``rollout_steps`` is not a multiple of T); the unfinished tail is carried
    to the next call, and is part of :meth:`state_dict` so a resumed run records exactly the same episodes.
    """

    def __init__(self) -> None:
        self._carry: dict[str, torch.Tensor] = {}  # "actions" [t, N, A], "values" [t, N]

    def collect(self, rollout: Any, episode_infos: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
        """Episodes finished in ``rollout`` (``actions [T, N, A]``, ``values [T, N]``, ``episode_returns [T, N]``,
        ``dones [T, N]``; mapping or attributes) with ``episode_infos`` (one info per step where they finished,
        holding ``final_grids [N, ρ, ρ, ρ]`` and ``metrics`` {name: [N]}).

        An episode's reward is ``episode_returns`` at its last step: the learner's one computation of the raw
        return (``PPO.collect``), never a sum of the rollout's rewards, which are what PPO trained on (scaled with
        ``reward_norm``, shaped with ``dense_every``).

        Returns ``None`` when no episode finished, else numpy arrays: ``actions [E, T, A]``, ``values [E, T]``,
        ``rewards [E]`` (returns), ``final_grids [E, ρ, ρ, ρ] uint8``, ``yaw [E] int8`` (``info["yaw"]``, else 0),
        ``metrics`` {name: [E]}, E = N · finishes.
        """
        steps = {k: _field(rollout, k).detach() for k in ("actions", "values")}
        returns = _field(rollout, "episode_returns").detach()  # [T, N]
        steps["values"] = steps["values"].reshape(returns.shape)  # [T, N, 1] critics squeeze to [T, N]
        dones = _field(rollout, "dones").detach().bool()  # [T, N]
        ended = dones.any(dim=1)
        if not torch.equal(ended, dones.all(dim=1)):
            raise ValueError("rollout.dones: environments must finish in lock-step (a row is all True or all False)")
        rows = torch.nonzero(ended).flatten().tolist()  # a handful per rollout: a short Python loop is fine
        if len(rows) != len(episode_infos):
            raise ValueError(f"episode_infos has {len(episode_infos)} entries but the rollout ends episodes {len(rows)} times")
        if self._carry:
            steps = {k: torch.cat([self._carry[k].to(v.device), v]) for k, v in steps.items()}
            offset = len(self._carry["actions"])
        else:
            offset = 0
        episodes: dict[str, list[np.ndarray]] = {"actions": [], "values": [], "rewards": [], "final_grids": [],
                                                 "yaw": []}
        metrics: dict[str, list[np.ndarray]] = {}
        start = 0
        for row, info in zip(rows, episode_infos, strict=True):
            stop = row + offset + 1
            episodes["actions"].append(_np(steps["actions"][start:stop].transpose(0, 1)))  # [N, T, A]
            episodes["values"].append(_np(steps["values"][start:stop].transpose(0, 1)))  # [N, T]
            episodes["rewards"].append(_np(returns[row]))  # [N]
            episodes["final_grids"].append(_np(info["final_grids"]).astype(np.uint8))
            yaw = info.get("yaw")
            episodes["yaw"].append(np.zeros(len(returns[row]), np.int8) if yaw is None else _np(yaw).astype(np.int8))
            for name, value in (info.get("metrics") or {}).items():
                metrics.setdefault(name, []).append(_np(torch.as_tensor(value)).astype(np.float32))
            start = stop
        self._carry = {k: v[start:].clone() for k, v in steps.items()} if start < len(steps["actions"]) else {}
        if not rows:
            return None
        out: dict[str, Any] = {k: np.concatenate(v) for k, v in episodes.items()}
        out["metrics"] = {k: np.concatenate(v) for k, v in metrics.items()}
        return out

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {k: v.cpu() for k, v in self._carry.items()}

    def load_state_dict(self, state: Mapping[str, torch.Tensor]) -> None:
        # (checkpoints before the returns were read from the learner also carried "rewards": no longer needed)
        self._carry = {k: v.clone() for k, v in state.items() if k in ("actions", "values")}


__all__ = [
    "RECORDS_DIR",
    "placed",
    "EpisodeCollector",
    "EpochRecord",
    "iter_records",
    "list_records",
    "read_record",
    "record_path",
    "write_record",
]
