"""The one place that initialises Taichi and makes its arrays (so that a switch to a fork such as `quadrants` stays
here); besides this module only the kernel modules (access, quat, links, voxels, clock, schedules) import Taichi.

Taichi can be initialised once per process. ``ensure(arch)`` does it on first use — never at import — and
later calls check that the request matches what is running. Arrays are Taichi ndarrays, created only through
``ndarray``/``from_numpy`` below; kernels take them as arguments, so one compiled kernel serves every batch size
(and Taichi's offline kernel cache, on by default, carries compiled kernels across processes).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import numpy as np
import taichi as ti

ARCHS = ("auto", "cpu", "cuda")
_active: str | None = None  # "cpu" or "cuda" once initialised


def ensure(arch: str = "auto") -> str:
    """Initialise Taichi once for ``arch`` ("auto" | "cpu" | "cuda") and return the active arch ("cpu" | "cuda").

    "auto" prefers CUDA and falls back to the CPU with a warning; "cuda" where no CUDA device exists is an error.
    """
    global _active
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
    if _active is None:
        want = ti.cpu if arch == "cpu" else ti.cuda
        ti.init(arch=want, log_level=ti.WARN, offline_cache=True)
        got = "cuda" if ti.lang.impl.current_cfg().arch == ti.cuda else "cpu"
        if arch == "cuda" and got != "cuda":
            # Taichi silently fell back to the CPU; the caller asked for a GPU, so say so.
            ti.reset()
            raise RuntimeError(
                "arch='cuda' requested but Taichi found no usable CUDA device (no driver or GPU visible); "
                "use arch='cpu', or arch='auto' to take CUDA where it exists and the CPU elsewhere"
            )
        if arch == "auto" and got != "cuda":
            warnings.warn("freeform.sim: no CUDA device found, simulating on the CPU", RuntimeWarning, stacklevel=3)
        _active = got
    elif arch != "auto" and arch != _active:
        raise RuntimeError(f"Taichi is already initialised on {_active!r} in this process; cannot switch to {arch!r}")
    return _active


def real(precision: str):
    """Taichi float type for "f32" | "f64"."""
    return ti.f64 if precision == "f64" else ti.f32


_TI_DTYPES = {np.dtype(np.float32): ti.f32, np.dtype(np.float64): ti.f64, np.dtype(np.int32): ti.i32}


def ndarray(dtype: np.dtype, shape: tuple[int, ...], rows_as_vectors: bool = False) -> ti.Ndarray:
    """An uninitialised Taichi ndarray of numpy ``dtype`` (float32/float64/int32) and ``shape``.

    rows_as_vectors: ``shape`` ``(n, c)`` gives a 1-D ndarray of n ``c``-vectors (same memory, C order).
    """
    if np.dtype(dtype) not in _TI_DTYPES:
        raise ValueError(f"dtype must be float32, float64 or int32, got {dtype}")
    ti_dtype = _TI_DTYPES[np.dtype(dtype)]
    if rows_as_vectors:
        if len(shape) != 2:
            raise ValueError(f"rows_as_vectors needs a 2-D shape, got {shape}")
        return ti.ndarray(ti.types.vector(shape[1], ti_dtype), shape[0])
    return ti.ndarray(ti_dtype, shape)


def upload(arr: ti.Ndarray, a: np.ndarray) -> None:
    """Copy host array ``a`` into the existing ndarray ``arr`` (same shape; a vector ndarray ``[n]`` of c-vectors
    takes ``[n, c]``). No new device array is made."""
    with _quiet_unrolling():
        arr.from_numpy(np.ascontiguousarray(a))  # (a transposed view is copied into C order here)


def from_numpy(a: np.ndarray, rows_as_vectors: bool = False) -> ti.Ndarray:
    """A new Taichi ndarray holding a copy of ``a`` (dtype float32/float64/int32).

    rows_as_vectors: ``a`` ``[n, c]`` becomes a 1-D ndarray of n ``c``-vectors (same memory, C order).
    """
    arr = ndarray(a.dtype, a.shape, rows_as_vectors)
    upload(arr, a)
    return arr


def to_numpy(arr: ti.Ndarray) -> np.ndarray:
    """Host copy of a Taichi ndarray (a vector ndarray ``[n]`` of c-vectors comes back as ``[n, c]``)."""
    with _quiet_unrolling():
        return arr.to_numpy()


@contextlib.contextmanager
def _quiet_unrolling() -> Iterator[None]:
    """Taichi copies vector ndarrays with its own kernels that unroll over the vector (≈ 40 columns here) and
    warn about compile time the first time; they compile in well under a second, once (offline cache)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="You are unrolling more than", category=SyntaxWarning)
        yield


def sync() -> None:
    """Wait for every launched kernel to finish (timings)."""
    ti.sync()


def num_threads() -> int:
    """Threads Taichi's CPU backend runs a parallel loop on (1 on CUDA: not meaningful there)."""
    cfg = ti.lang.impl.current_cfg()
    return int(cfg.cpu_max_num_threads) if cfg.arch != ti.cuda else 1
