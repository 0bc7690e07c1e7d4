"""Fixtures shared by the test modules (opt in with ``pytestmark = pytest.mark.usefixtures(...)``)."""

import os
import random

import numpy as np
import pytest
import torch

# Keep the suite's thread use predictable on a 2-core CI machine.
os.environ.setdefault("OMP_NUM_THREADS", "2")


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
