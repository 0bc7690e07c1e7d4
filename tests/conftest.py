"""Fixtures shared by the test modules (opt in with ``pytestmark = pytest.mark.usefixtures(...)``)."""

import os
import random

import numpy as np
import pytest
import torch

# Keep the suite's thread use predictable on a 2-core CI machine.
os.environ.setdefault("OMP_NUM_THREADS", "2")
# The suite runs the physics on the strict path (no fast-math: the floating-point program is the source's, so the
# same bits on any x86-64 CPU) unless the caller chose: `make test` runs the simulator's tests a second time with
# fast-math on, the production path. Set before any kernel is built (docs/physics-running.md, "Host independence").
os.environ.setdefault("FREEFORM_FAST_MATH", "0")


def physics_path() -> str:
    """The physics path this process's tests ran on, in one line."""
    from freeform.sim import runtime

    strict = not runtime.fast_math()
    reference = ("reference tests run (strict IEEE: host-independent)" if strict else
                 "reference tests skipped (they hold on the strict path, FREEFORM_FAST_MATH=0)")
    return (f"physics: {runtime.describe()} on the CPU, f32 and f64 (references: f64), fast-math "
            f"{'off' if strict else 'on'} ({runtime.FAST_MATH_ENV_VAR}); {reference}; CPU {runtime.cpu_features()}")


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Once per run, beside the results (also under -q): which physics path ran, so a failure on someone's
    machine reads at a glance."""
    terminalreporter.write_line(physics_path())


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Files holding a ``slow`` test run first, so that under ``make test``'s xdist workers (whole files each, in
    this order: ``--no-loadscope-reorder``; without it xdist orders files by test count) the last files to start
    are short ones and both workers finish together: xdist's own order left a 38 s file last and one worker idle. Reference tests check the strict path's claim; a
    fast-math process compiles another program, whose results depend on the host CPU's vector features
    (docs/physics.md): they are skipped there, saying why."""
    from freeform.sim import runtime

    # (markers, not `in item.keywords`: keywords hold every name up the tree, a folder's among them)
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: the collection's order within each group
    if not runtime.fast_math():
        return
    skip = pytest.mark.skip(reason="a reference test: holds on the strict path (FREEFORM_FAST_MATH=0); this process "
                                   "compiles with fast-math, whose rounding depends on the host CPU")
    for item in items:
        if item.get_closest_marker("reference") is not None:
            item.add_marker(skip)


@pytest.fixture
def one_thread():
    """Small workloads: one intra-op thread. On a shared 2-core machine, two OpenMP threads per process spin
    against other processes and ran the learning test 20x slower (288 s vs 13 s) under load."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def keep_global_rng():
    """Leave torch's, numpy's and python's global RNGs as found, so that no test depends on which tests ran
    before it (some build networks from the global RNG)."""
    torch_state, np_state, py_state = torch.get_rng_state(), np.random.get_state(), random.getstate()
    yield
    torch.set_rng_state(torch_state)
    np.random.set_state(np_state)
    random.setstate(py_state)
