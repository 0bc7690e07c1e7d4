"""The CPU step compiled by the host's C++ compiler: the ``native`` schedule (docs/physics-native.md, "The native schedule").

Taichi compiles the simulator's kernels to scalar code (docs/physics.md, "SIMD across links, probed"); the same
link and voxel updates written once in C++ (``native_step.cpp``, GCC's vector extensions: a group of links or voxels
per vector instruction along the common path, as many as the target's registers hold — 16 with AVX-512, 8 with AVX2
— Voxelyze's branches for the rest) run 2.4–3.3× as fast per thread as Taichi's. The engine keeps its Taichi
buffers and every other kernel (layout, transfers, commands, senses, snapshots); only the stepping runs here, on
the three buffers themselves, which this schedule keeps in host memory (numpy arrays the CPU's kernels take in
place: ``Engine._advance``).

What it runs is the f32 production path: fast-math, Voxelyze semantics, a fixed dt, the flat floor (or none), any
actuation (the sine, commands, residual commands with their ramps), traces. ``schedule="auto"`` takes it on the CPU
for every such batch where a compiler built it for AVX2 or AVX-512 (``usable``; ``schedules.resolve_schedule``
decides), the robots schedule otherwise; ``schedule="native"`` refuses anything else naming the setting
(``unsupported``).

The library is compiled on first use (g++, or ``$CXX``; ``-march=native``) into ``$FREEFORM_NATIVE_CACHE``
(default ``~/.cache/freeform/native``), one file per source, layout, flags, compiler and CPU, so a later process
loads it at once.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

SOURCE = Path(__file__).with_name("native_step.cpp")
# -ffast-math: the simulator's production path (the strict path stays Taichi's); -mtune lets g++ use the target's
# gather instructions; -fopenmp-simd hands the `omp simd` loops of cos, sin and pow to glibc's vector maths (no
# OpenMP runtime: plain threads share the robots)
FLAGS = ("-O3", "-ffast-math", "-fopenmp-simd", "-pthread", "-shared", "-fPIC", "-std=c++17")
CACHE_ENV_VAR = "FREEFORM_NATIVE_CACHE"
COMPILER_ENV_VAR = "CXX"
# the instruction set compiled for: this host's by default; another (e.g. x86-64-v3, what valgrind presents:
# scripts/profile_sim.py --schedule native; or a cluster's oldest node) through this variable
ARCH_ENV_VAR = "FREEFORM_NATIVE_ARCH"


def target() -> str:
    """The instruction set the step is built for: ``$FREEFORM_NATIVE_ARCH``, default "native" (this host's)."""
    return os.environ.get(ARCH_ENV_VAR) or "native"


def flags() -> tuple[str, ...]:
    """The compiler's flags: ``FLAGS`` and the target's ``-march``/``-mtune``."""
    arch = target()
    return (*FLAGS, f"-march={arch}", f"-mtune={'generic' if arch.startswith('x86-64') else arch}")
ENTRY_POINTS = ("advance", "links_vector", "links_voxels_scalar", "links_voxels_vector")
# the lanes of the builds measured faster than Taichi's step: AVX2's 8 and AVX-512's 16 (docs/physics.md)
MEASURED_LANES = (8, 16)


def unsupported(precision: str, switches: Any) -> str | None:
    """Why the native step cannot run a batch of this ``precision`` and these ``state.Switches`` (None: it can)."""
    from freeform.sim import runtime
    from freeform.sim.terrain import FLAT

    if precision != "f32":
        return f"precision={precision!r} (the native step is the f32 path's)"
    if not runtime.fast_math():
        return "FREEFORM_FAST_MATH=0 (the strict path's bits are Taichi's)"
    if switches.rl4design:  # (its slips, and its dynamic dt)
        return "semantics='rl4design'"
    if switches.terrain != FLAT:
        return "a terrain (sim.terrain)"
    return None


def compiler() -> str | None:
    """The C++ compiler's path ($CXX, else g++), None where there is none."""
    return shutil.which(os.environ.get(COMPILER_ENV_VAR, "g++"))


def layout_header() -> str:
    """``layout.h``: every column index and width of ``state.py``'s tables, the header's offsets, the flags, the
    statuses and the model's thresholds, as the C++ reads them (one source of the layout: state.py)."""
    from freeform.sim import clock, config, links, quat, voxels
    from freeform.sim import state as S

    lines = ["#pragma once"]
    for prefix, table in (("VR", S.VR), ("VI", S.VI), ("LR", S.LR), ("LI", S.LI), ("RT", S.RT), ("RI", S.RI),
                          ("MT", S.MT), ("LT", S.LT), ("GP", S.GP), ("HDR", S.HDR), ("SUMMARY", S.SUMMARY)):
        lines.append(f"constexpr int {prefix}_W = {table.width};")
        lines += [f"constexpr int {prefix}_{col} = {getattr(table, col)};" for col in table.columns]
    lines += [f"constexpr int FLAG_SMALL = {S.SMALL}, FLAG_VALID = {S.VALID};",
              f"constexpr int FLAG_STATIC = {S.STATIC}, FLAG_FIXED = {S.FIXED}, FLAG_CONTACT = {S.CONTACT};",
              f"constexpr int STATUS_RUNNING = {S.RUNNING}, STATUS_DONE = {S.DONE}, STATUS_DIVERGED = {S.DIVERGED}, "
              f"STATUS_STALLED = {S.STALLED};",
              f"constexpr int EV_SAMPLE = {S.EV_SAMPLE}, EV_START = {S.EV_START}, EV_END = {S.EV_END};",
              f"constexpr double NO_LIMIT = {S.NO_LIMIT!r}, TWO_PI = {clock.TWO_PI!r};",
              f"constexpr float SA_BEND = {links.SA_BOND_BEND_RAD}f, SA_EXT = {links.SA_BOND_EXT_PERC}f, "
              f"HYST = {links.HYSTERESIS_FACTOR}f;",
              f"constexpr float ATAN_SERIES_X2 = {quat.ATAN_SERIES_X2}f, POSX_SMALL = {quat.POSX_SMALL}f, "
              f"ROTVEC_SMALL4 = {quat.ROTVEC_SMALL4}f;",
              f"constexpr double POSX_PI_EPS = {quat.POSX_PI_EPS};",
              f"constexpr float RENORM_NEWTON = {voxels.RENORM_NEWTON}f, POISSON_SERIES_X = {voxels.POISSON_SERIES_X}f;",
              f"constexpr int POISSON_SERIES_TERMS = {config.POISSON_SERIES_TERMS};"]
    return "\n".join(lines) + "\n"


@functools.cache
def library() -> ctypes.CDLL:
    """The compiled step, loaded (compiled first where the cache has no build of this source, layout, flags,
    compiler and CPU). Raises RuntimeError naming what is missing or what the compiler said."""
    from freeform.sim import runtime

    cxx = compiler()
    if cxx is None:
        raise RuntimeError(f"schedule='native' needs a C++ compiler: no {os.environ.get(COMPILER_ENV_VAR, 'g++')} on "
                           "PATH (set $CXX, or use schedule='robots')")
    header, source = layout_header(), SOURCE.read_text()
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True).stdout
    key = hashlib.sha256("\0".join((source, header, " ".join(flags()), version, platform.machine(),
                                    runtime.cpu_features())).encode()).hexdigest()[:16]
    cache = Path(os.environ.get(CACHE_ENV_VAR) or Path.home() / ".cache" / "freeform" / "native")
    lib = cache / f"native_step_{key}.so"
    if not lib.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:
            (Path(tmp) / "layout.h").write_text(header)
            built = Path(tmp) / "native_step.so"
            done = subprocess.run([cxx, *flags(), f"-I{tmp}", "-o", str(built), str(SOURCE)], capture_output=True,
                                  text=True)
            if done.returncode != 0:
                raise RuntimeError(f"schedule='native': {cxx} could not compile {SOURCE.name}:\n{done.stderr[-3000:]}")
            os.replace(built, lib)  # (atomic: processes building at once each put a whole file)
    so = ctypes.CDLL(str(lib))
    pointers = [ctypes.c_void_p] * 3
    so.advance.argtypes = [*pointers, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int]
    so.advance.restype = ctypes.c_long
    for name in ENTRY_POINTS[1:]:
        getattr(so, name).argtypes = [*pointers, ctypes.c_int, ctypes.c_int]
        getattr(so, name).restype = ctypes.c_long
    so.lanes.restype, so.instruction_set.restype = ctypes.c_int, ctypes.c_char_p
    return so


def available() -> bool:
    """Whether the native step can be compiled and loaded here."""
    try:
        library()
    except (RuntimeError, OSError):
        return False
    return True


def built_for() -> str:
    """The instruction set the library was built for and its lanes, e.g. "AVX2, 8 lanes (-march=x86-64-v3)"."""
    so = library()
    return f"{so.instruction_set().decode()}, {so.lanes()} lanes (-march={target()})"


def faster_here() -> bool:
    """Whether the native step is measured faster than Taichi's for the instruction set it is built for here: AVX2
    (8 lanes; 2.4x per thread) and AVX-512 (16; 3.3x). A build of another width (4: SSE or NEON) is unmeasured, so
    Taichi's step stays (docs/physics-native.md, "The native schedule")."""
    return library().lanes() in MEASURED_LANES


def usable(precision: str, switches: Any) -> bool:
    """Whether ``schedule="auto"`` takes the native step on the CPU for a batch of this ``precision`` and these
    switches: it runs them (``unsupported``), a compiler built it and it is faster here (``faster_here``); else the
    robots schedule, silently."""
    return unsupported(precision, switches) is None and available() and faster_here()


def advance(reals: np.ndarray, ints: np.ndarray, f64s: np.ndarray, n_steps: int, threads: int, switches: Any) -> int:
    """``n_steps`` steps of every robot still stepping, in place on the engine's three host buffers
    (``state.BUFFERS``: f32, i32, f64, C-contiguous), the robots shared among ``threads`` workers. Returns the
    item-steps that left the vector path (the branching updates': a measure of its coverage)."""
    for name, a, dtype in (("reals", reals, np.float32), ("ints", ints, np.int32), ("f64s", f64s, np.float64)):
        if a.dtype != dtype or not a.flags.c_contiguous:
            raise ValueError(f"native.advance: {name} must be a C-contiguous {np.dtype(dtype).name} array, got "
                             f"{a.dtype} (contiguous: {a.flags.c_contiguous})")
    return int(library().advance(reals.ctypes.data, ints.ctypes.data, f64s.ctypes.data, int(n_steps), int(threads),
                                 int(switches.floor), int(switches.command)))
