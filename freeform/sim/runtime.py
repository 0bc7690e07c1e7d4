"""The one place that knows which Taichi backend runs the kernels, initialises it and makes its arrays.

Two backends run the same kernels: **Taichi 1.7.4** (``taichi``, the default install) and Genesis AI's maintained
fork **quadrants** (``pip install 'freeform[quadrants]'``), whose API is Taichi's under another name. The choice:
``SimConfig.backend`` (``sim.backend=quadrants``), else the environment variable ``FREEFORM_BACKEND``, else
"taichi". The kernel modules (access, quat, links, voxels, clock, schedules) take ``ti`` from here
(``from freeform.sim.runtime import ti``): a stand-in module that forwards every attribute to the chosen backend,
so that importing freeform imports neither, and the backend is fixed the first time a kernel is built or
``ensure`` runs. One backend per process: the two cannot both be initialised in one (a request for the other one
after that is an error; run it in a new process).

A backend is initialised once per process. ``ensure(arch)`` does it on first use — never at import — and later
calls check that the request matches what is running. Arrays are ndarrays, created only through
``ndarray``/``from_numpy`` below; kernels take them as arguments, so one compiled kernel serves every batch size
(and the offline kernel cache, on by default, carries compiled kernels across processes).
"""

from __future__ import annotations

import contextlib
import importlib
import os
import types
import warnings
from collections.abc import Iterator
from importlib import metadata

import numpy as np

ARCHS = ("auto", "cpu", "cuda")
BACKENDS = ("taichi", "quadrants")
ENV_VAR = "FREEFORM_BACKEND"
FAST_MATH_ENV_VAR = "FREEFORM_FAST_MATH"
_active: str | None = None  # "cpu" or "cuda" once initialised
_backend: str | None = None  # the backend's name once fixed (a kernel built, or ensure called)
_module: types.ModuleType | None = None


def requested(backend: str | None = None) -> str:
    """The backend a process asks for: ``backend`` if given, else ``$FREEFORM_BACKEND``, else "taichi"."""
    name = backend if backend is not None else (os.environ.get(ENV_VAR) or "taichi")
    if name not in BACKENDS:
        source = "backend" if backend is not None else ENV_VAR
        raise ValueError(f"{source} must be one of {BACKENDS}, got {name!r}")
    return name


def backend() -> str | None:
    """The backend in use in this process ("taichi" | "quadrants"), or None while none is fixed yet."""
    return _backend


def describe(backend: str | None = None) -> str:
    """"<name> <version>" of the backend in use, or else of the one ``backend`` (or the environment) asks for —
    for provenance (``run_info.json``); reads the installed version without importing it."""
    name = _backend or requested(backend)
    try:
        return f"{name} {metadata.version(name)}"
    except metadata.PackageNotFoundError:
        return f"{name} (not installed)"


def use(backend: str | None = None) -> types.ModuleType:
    """Fix this process's backend (``requested(backend)``) and return its module; the same again, or None once one
    is fixed, is a no-op.

    Raises ImportError naming the extra when it is not installed, and RuntimeError when another backend is already
    in use in this process (Taichi and quadrants cannot both be initialised in one process).
    """
    global _backend, _module
    if backend is None and _backend is not None:  # no explicit choice: whichever is in use
        return _module
    name = requested(backend)
    if _backend is not None:
        if name != _backend:
            state = f"initialised on {_active!r}" if _active is not None else "in use (kernels built with it)"
            raise RuntimeError(
                f"freeform.sim: backend {name!r} requested, but {_backend!r} is already {state} in this process; "
                f"Taichi and quadrants cannot both run in one process. Choose the backend before the first "
                f"simulation (sim.backend=... or {ENV_VAR}=...), or run the other one in a new process")
        return _module
    try:
        module = importlib.import_module(name)
    except ImportError as e:
        extra = "quadrants" if name == "quadrants" else None
        how = f"pip install 'freeform[{extra}]' (or pip install {name})" if extra else f"pip install {name}"
        raise ImportError(f"freeform.sim: backend {name!r} is not installed ({e}); {how}") from e
    _backend, _module = name, module
    return module


def fast_math() -> bool:
    """Whether kernels compile with fast-math (both backends' default, on). ``FREEFORM_FAST_MATH=0`` is the strict
    path: LLVM keeps the source's IEEE arithmetic (no fused multiply-adds, no reassociation), so the result does not
    depend on which x86-64 CPU compiles it, the two schedules and the two backends give the same bits, and the
    reference tests hold (the suite's default; docs/physics-running.md, "Host independence"), at ~7 % of speed."""
    flag = os.environ.get(FAST_MATH_ENV_VAR, "1")
    if flag not in ("0", "1"):
        raise ValueError(f"{FAST_MATH_ENV_VAR} must be 0 or 1, got {flag!r}")
    return flag == "1"


def cpu_features() -> str:
    """The host CPU's vector features that decide what the JIT emits under fast-math ("AVX+FMA3+AVX2+AVX512F"),
    read through CPUID by numpy — an emulator's CPU, not the host's /proc (docs/physics-running.md, "Host independence")."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as features
    return "+".join(f for f in ("SSE42", "AVX", "FMA3", "AVX2", "AVX512F") if features.get(f)) or "without SSE4.2"


class _Backend(types.ModuleType):
    """``ti``: forwards every attribute to the backend module (fixing it on first use). A module subclass, so that
    Taichi's and quadrants' AST front-ends resolve ``ti.func``, ``ti.static``... through it as through the module."""

    def __getattr__(self, attr: str):
        return getattr(_module if _module is not None else use(), attr)


ti = _Backend("freeform.sim.runtime.ti")


def ensure(arch: str = "auto", backend: str | None = None) -> str:
    """Initialise the backend (``requested(backend)``) once for ``arch`` ("auto" | "cpu" | "cuda") and return the
    active arch ("cpu" | "cuda").

    "auto" prefers CUDA and falls back to the CPU with a warning; "cuda" where no CUDA device exists is an error.
    A different backend than the one already in use in this process is an error (``use``).
    """
    global _active
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
    use(backend)
    if _active is None:
        want = ti.cpu if arch == "cpu" else ti.cuda
        options = {}
        if arch == "cpu" and "TI_ADVANCED_OPTIMIZATION" not in os.environ:
            # The backend's own IR passes cost 2/3 of a kernel's compile (10 s -> 3-4 s per variant) and nothing at
            # run time on the CPU, where LLVM optimises the same code; on the strict path the program is the same
            # bits either way (docs/physics-running.md, "Compile time"). CUDA keeps them (unmeasured there).
            options["advanced_optimization"] = False
        ti.init(arch=want, log_level=ti.WARN, offline_cache=True, fast_math=fast_math(), **options)
        got = "cuda" if ti.lang.impl.current_cfg().arch == ti.cuda else "cpu"
        if arch == "cuda" and got != "cuda":
            # the backend silently fell back to the CPU; the caller asked for a GPU, so say so.
            ti.reset()
            raise RuntimeError(
                f"arch='cuda' requested but {_backend} found no usable CUDA device (no driver or GPU visible); "
                "use arch='cpu', or arch='auto' to take CUDA where it exists and the CPU elsewhere"
            )
        if arch == "auto" and got != "cuda":
            warnings.warn("freeform.sim: no CUDA device found, simulating on the CPU", RuntimeWarning, stacklevel=3)
        _active = got
    elif arch != "auto" and arch != _active:
        raise RuntimeError(f"{_backend} is already initialised on {_active!r} in this process; "
                           f"cannot switch to {arch!r}")
    return _active


def real(precision: str):
    """The backend's float type for "f32" | "f64"."""
    return ti.f64 if precision == "f64" else ti.f32


def _ti_dtype(dtype: np.dtype):
    return {np.dtype(np.float32): ti.f32, np.dtype(np.float64): ti.f64, np.dtype(np.int32): ti.i32}.get(dtype)


def ndarray(dtype: np.dtype, shape: tuple[int, ...], rows_as_vectors: bool = False) -> ti.Ndarray:
    """An uninitialised Taichi ndarray of numpy ``dtype`` (float32/float64/int32) and ``shape``.

    rows_as_vectors: ``shape`` ``(n, c)`` gives a 1-D ndarray of n ``c``-vectors (same memory, C order).
    """
    ti_dtype = _ti_dtype(np.dtype(dtype))
    if ti_dtype is None:
        raise ValueError(f"dtype must be float32, float64 or int32, got {dtype}")
    if rows_as_vectors:
        if len(shape) != 2:
            raise ValueError(f"rows_as_vectors needs a 2-D shape, got {shape}")
        return ti.ndarray(ti.types.vector(shape[1], ti_dtype), shape[0])
    return ti.ndarray(ti_dtype, shape)


def upload(arr: ti.Ndarray | np.ndarray, a: np.ndarray) -> None:
    """Copy host array ``a`` into the existing ndarray ``arr`` (same shape; a vector ndarray ``[n]`` of c-vectors
    takes ``[n, c]``; a numpy array, which the CPU's kernels also take, is written in place). No new device array
    is made."""
    if isinstance(arr, np.ndarray):
        arr[...] = a
        return
    with _quiet_unrolling():
        arr.from_numpy(np.ascontiguousarray(a))  # (a transposed view is copied into C order here)


def from_numpy(a: np.ndarray, rows_as_vectors: bool = False) -> ti.Ndarray:
    """A new Taichi ndarray holding a copy of ``a`` (dtype float32/float64/int32).

    rows_as_vectors: ``a`` ``[n, c]`` becomes a 1-D ndarray of n ``c``-vectors (same memory, C order).
    """
    arr = ndarray(a.dtype, a.shape, rows_as_vectors)
    upload(arr, a)
    return arr


def to_numpy(arr: ti.Ndarray | np.ndarray) -> np.ndarray:
    """Host copy of a Taichi ndarray (a vector ndarray ``[n]`` of c-vectors comes back as ``[n, c]``), or of a
    numpy array standing in for one."""
    if isinstance(arr, np.ndarray):
        return arr.copy()
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
    """Threads the CPU backend runs a parallel loop on (1 on CUDA: not meaningful there)."""
    cfg = ti.lang.impl.current_cfg()
    return int(cfg.cpu_max_num_threads) if cfg.arch != ti.cuda else 1
