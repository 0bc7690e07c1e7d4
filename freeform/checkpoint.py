"""Checkpoints that survive a kill at any moment, and the RNG states that make a resumed run exact.

A run directory keeps ``checkpoints/last.pt`` (rewritten every epoch) plus numbered ``checkpoints/epoch_<e>.pt``.
:func:`save_checkpoint` writes through ``freeform.files.write_atomically``: a temporary file in the same directory, flushed to disk and renamed over
the target (``os.replace`` is atomic on POSIX and Windows), so a reader sees either the old file or the new one,
never a half-written one; a write that fails (disk full, quota, a vanished mount) raises the ``OSError`` that says
so, removes the temporary file and leaves the target as it was. :func:`load_checkpoint` turns any failure to read a file into a
:class:`CheckpointError` that names it (and lists the other checkpoints next to it).

Checkpoints are loaded with ``torch.load(weights_only=True)``: they hold only tensors, numbers, strings and
containers (RNG states are converted to tensors), so loading a file cannot run code.

This is the one checkpoint path: ``PPO.save``/``PPO.load`` and the trainer's run checkpoints both go through
:func:`save_checkpoint`/:func:`load_checkpoint`. A PPO checkpoint holds ``policy_class``, ``policy_kwargs``,
``ppo_config``, ``epoch``, ``global_step`` and ``ppo`` (``PPO.state_dict()``); a run checkpoint is a learner's
``checkpoint()`` (``freeform.learner``: PPO's, or ``algo`` and ``evolution``) plus the run's ``config`` and ``rng``. Files of earlier versions are upgraded on load (:func:`_upgrade`).

Large tensors that are mostly zeros (a distillation's dataset: observations that are zero outside the bodies)
are written as their non-zero elements and a bit mask (:func:`pack_sparse`), and read back bit for bit.
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freeform.files import write_atomically

CHECKPOINT_DIR = "checkpoints"
LAST = "last.pt"
FORMAT = "freeform-checkpoint"
VERSION = 4
"""4: large tensors of mostly zeros packed (:func:`pack_sparse`); 3: the episodes cut by a rollout's end (a run's ``collector``) inside the learner's state, as PPO's
``episode_carry``; 2: per-environment state named under ``per_env`` keys. Version 2 files load (one upgrade
step); version 1 was never released and is refused."""


class CheckpointError(ValueError):
    """A checkpoint file is missing, truncated, corrupt, not a freeform checkpoint, or does not fit."""


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """There is no checkpoint file at the path."""


class CheckpointWriteError(CheckpointError):
    """A run could not write its checkpoint (or the epoch's files that must be on disk before it): disk full, quota,
    a vanished mount. The message names what failed and which checkpoint is still the run's last good one."""


def numbered_name(epoch: int) -> str:
    """File name of the checkpoint taken after ``epoch`` epochs: ``epoch_000123.pt``."""
    return f"epoch_{epoch:06d}.pt"


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> Path:
    """Write ``state`` to ``path`` atomically (temporary file in the same directory, fsync, rename).

    ``state`` is stamped with ``format``/``version`` keys. Returns the path written.
    """
    payload = {"format": FORMAT, "version": VERSION, **pack_sparse(state)}

    def write(f: Any) -> None:
        sink = _Sink(f)
        try:
            torch.save(payload, sink)
        except Exception as exc:
            if sink.error is not None:  # torch words a failed write as a RuntimeError about zip offsets
                raise sink.error from exc
            raise

    return write_atomically(path, write)


class _Sink:
    """The file ``torch.save`` writes to, remembering the first ``OSError`` (disk full, quota, a vanished mount):
    torch reports such a failure as ``RuntimeError: [enforce fail at inline_container.cc] unexpected pos``, so
    :func:`save_checkpoint` raises the ``OSError`` instead, which says what happened."""

    def __init__(self, file: Any) -> None:
        self.file = file
        self.error: OSError | None = None

    def write(self, data: Any) -> int:
        try:
            return self.file.write(data)
        except OSError as exc:
            self.error = self.error or exc
            raise

    def flush(self) -> None:
        self.file.flush()


def _siblings(path: Path) -> str:
    """What to do instead: the other checkpoints beside ``path`` (resume from one of them), or a new run."""
    others = sorted(p.name for p in path.parent.glob("*.pt") if p != path) if path.parent.is_dir() else []
    if others:
        return (f"; other checkpoints in {path.parent}: {others} — resume from one of them with "
                f"trainer.resume={path.parent / others[-1]}")
    return "; no other checkpoint beside it: start a new run (without trainer.resume)"


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Packed tensors (:func:`pack_sparse`) come back as they were saved. Raises :class:`CheckpointError` naming
    ``path`` if it is missing, unreadable, truncated, corrupt or not a
    freeform checkpoint. Nothing is written.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointNotFoundError(f"checkpoint {path} does not exist{_siblings(path)}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises a variety (RuntimeError, EOFError, UnpicklingError, ...)
        # Only the cause's first line: torch's weights_only text goes on to advise weights_only=False, which would
        # run code from an untrusted file and would not repair a truncated one.
        cause = next((line.strip() for line in str(exc).splitlines() if line.strip()), "")
        raise CheckpointError(
            f"checkpoint {path} is unreadable (truncated or corrupt?): {type(exc).__name__}: {cause}{_siblings(path)}"
        ) from exc
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path} is not a freeform checkpoint (no format={FORMAT!r} key)")
    if state.get("version") not in range(2, VERSION + 1):
        raise CheckpointError(f"checkpoint {path} has version {state.get('version')!r}; this freeform reads 2 to {VERSION}")
    return _upgrade(unpack_sparse(state, map_location))


PACKED = "freeform-packed-tensor"
"""The marker key of a packed tensor in a checkpoint: ``{PACKED: shape, "mask": uint8 bits, "values": ...}``."""
PACK_MIN_ELEMENTS = 1 << 20
"""Tensors smaller than this are written as they are (packing would save too little to pay for its time)."""
PACK_MAX_RATIO = 0.75
"""A tensor is packed when its packed form (two bits per element, the non-zero elements) takes at most this
fraction of its bytes."""
_BITS_AS = {2: torch.int16, 4: torch.int32, 8: torch.int64}
_PACKABLE = (torch.bool, torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64, torch.float16,
             torch.bfloat16, torch.float32, torch.float64)
"""The dtypes packed (others — quantized, float8, complex — are written as they are)."""


def pack_sparse(state: Any) -> Any:
    """``state`` with every tensor of ≥ :data:`PACK_MIN_ELEMENTS` elements that is mostly zeros replaced by its
    packed form: its non-zero elements (NaN and subnormals among them, compared by their bits), a bit mask of where
    they are and one of its −0.0s (masking by zero, ``x * filled``, leaves them). Containers (dict, list, tuple)
    are walked and returned as they were where nothing in them is packed; all else is returned as is."""
    return _map_leaves(state, _packed)


def unpack_sparse(state: Any, map_location: str | torch.device = "cpu") -> Any:
    """Inverse of :func:`pack_sparse`: each packed tensor rebuilt bit for bit (on ``map_location``)."""
    return _map_leaves(state, lambda leaf: _unpacked(leaf, map_location))


def _map_leaves(state: Any, leaf: Any) -> Any:
    """``state`` with ``leaf`` applied to everything that is not a container (a packed tensor's dict is a leaf);
    a container whose leaves all come back as they were is returned itself (its type and metadata kept)."""
    if isinstance(state, dict) and PACKED not in state:
        mapped = {k: _map_leaves(v, leaf) for k, v in state.items()}
        return state if all(mapped[k] is v for k, v in state.items()) else mapped
    if isinstance(state, (list, tuple)):
        items = [_map_leaves(v, leaf) for v in state]
        if all(a is b for a, b in zip(items, state, strict=True)):
            return state
        return type(state)(*items) if hasattr(state, "_fields") else type(state)(items)
    return leaf(state)


def _packed(x: Any) -> Any:
    """A tensor's packed form where it is large and mostly zeros (:func:`pack_sparse`), else ``x`` itself."""
    if not isinstance(x, torch.Tensor) or x.numel() < PACK_MIN_ELEMENTS or x.layout != torch.strided \
            or x.dtype not in _PACKABLE:
        return x
    flat = x.detach().reshape(-1).cpu()
    if flat.is_floating_point():
        bits = flat.view(_BITS_AS[flat.element_size()])
        sign = torch.tensor(1, dtype=bits.dtype) << (8 * flat.element_size() - 1)
        nonzero, negative_zero = (bits & ~sign) != 0, bits == sign
    else:
        nonzero, negative_zero = flat != 0, None
    kept = int(nonzero.sum())
    if flat.numel() / 4 + kept * flat.element_size() > PACK_MAX_RATIO * flat.numel() * flat.element_size():
        return x
    packed = {PACKED: list(x.shape), "mask": _bits(nonzero), "values": flat[nonzero].clone()}
    if negative_zero is not None:
        packed["negative_zeros"] = _bits(negative_zero)
    return packed


def _unpacked(leaf: Any, map_location: str | torch.device) -> Any:
    """A packed tensor's dict rebuilt bit for bit on ``map_location``; any other leaf as it is."""
    if not (isinstance(leaf, dict) and PACKED in leaf):
        return leaf
    shape, values = leaf[PACKED], leaf["values"].cpu()
    n = int(np.prod(shape, dtype=np.int64))
    out = torch.zeros(n, dtype=values.dtype)
    out[_unbits(leaf["mask"], n)] = values
    if "negative_zeros" in leaf:
        out[_unbits(leaf["negative_zeros"], n)] = -0.0
    return out.reshape(shape).to(map_location)


def _bits(mask: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(np.packbits(mask.numpy()))


def _unbits(bits: torch.Tensor, n: int) -> torch.Tensor:
    return torch.from_numpy(np.unpackbits(bits.cpu().numpy(), count=n).view(np.bool_))


def _upgrade(state: dict[str, Any]) -> dict[str, Any]:
    """A version-2 run checkpoint in today's layout: the run's episode collector moved into the learner's state
    (evolution's carried nothing); version 3 differs from 4 only in writing no packed tensors."""
    if state["version"] == 2:
        carry = state.get("collector") or {}
        state = {**{k: v for k, v in state.items() if k != "collector"}, "version": VERSION}
        if isinstance(state.get("ppo"), dict):
            state["ppo"] = {**state["ppo"], "episode_carry": dict(carry)}
    return state


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """``trainer.resume`` -> the checkpoint file: a file as is; a run directory -> ``<dir>/checkpoints/last.pt``."""
    path = Path(path).expanduser()
    if path.is_dir():
        inner = path / CHECKPOINT_DIR / LAST
        if not inner.is_file() and (path / LAST).is_file():  # the checkpoints directory itself
            inner = path / LAST
        return inner
    return path


AUTO = "auto"
"""``trainer.resume=auto``: continue the run directory's own checkpoint when there is one (:func:`auto_checkpoint`)."""


def auto_checkpoint(run_dir: str | os.PathLike[str]) -> Path | None:
    """What ``trainer.resume=auto`` continues from: ``<run_dir>/checkpoints/last.pt`` if it exists, else None (start
    fresh). Only ``last.pt`` counts: a run killed before finishing its first epoch has none, and starting it again
    from scratch is the same run (same seed)."""
    path = Path(run_dir) / CHECKPOINT_DIR / LAST
    return path if path.is_file() else None


def run_dir_of(path: str | os.PathLike[str]) -> Path:
    """The run directory a ``trainer.resume`` value belongs to (``<run>/checkpoints/x.pt`` -> ``<run>``)."""
    path = Path(path).expanduser()
    if path.is_dir():
        return path.parent if path.name == CHECKPOINT_DIR else path
    parent = path.parent
    return parent.parent if parent.name == CHECKPOINT_DIR else parent


def capture_rng_state() -> dict[str, Any]:
    """The global RNG states of python, numpy and torch (CPU and every CUDA device), as tensors and ints.

    numpy's MT19937 state becomes a uint32 tensor so that the checkpoint stays loadable with ``weights_only``.
    """
    algo, keys, pos, has_gauss, cached = np.random.get_state(legacy=True)  # type: ignore[misc]
    py_version, py_state, py_gauss = random.getstate()
    state: dict[str, Any] = {
        "python": {"version": py_version, "state": torch.tensor(py_state, dtype=torch.int64), "gauss": py_gauss},
        "numpy": {
            "algorithm": algo,
            "keys": torch.from_numpy(np.asarray(keys, dtype=np.uint32).astype(np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state`."""
    py = state["python"]
    random.setstate((py["version"], tuple(int(v) for v in py["state"].tolist()), py["gauss"]))
    npy = state["numpy"]
    np.random.set_state(
        (npy["algorithm"], npy["keys"].numpy().astype(np.uint32), npy["pos"], npy["has_gauss"], npy["cached_gaussian"])
    )
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


__all__ = [
    "AUTO",
    "CHECKPOINT_DIR",
    "LAST",
    "CheckpointError",
    "CheckpointNotFoundError",
    "CheckpointWriteError",
    "auto_checkpoint",
    "capture_rng_state",
    "load_checkpoint",
    "numbered_name",
    "pack_sparse",
    "resolve_checkpoint",
    "restore_rng_state",
    "run_dir_of",
    "save_checkpoint",
    "unpack_sparse",
]
