"""The engine's numerical shortcuts against independent truth: scipy's rotation vectors and the exact power law.

The f32 kernels take shortcuts for speed (docs/physics.md, "CPU speed"): atan's series for small rotation vectors,
the binomial series for the Poisson strain. These tests pin each shortcut to the exact formula across its switch
point, so a change that breaks one branch cannot hide behind the end-to-end tolerances.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import binom

from freeform.sim import SimConfig, runtime
from freeform.sim.config import MAT_COLUMNS, POISSON_SERIES_TERMS, Material, material_table
from freeform.sim.quat import ATAN_SERIES_X2
from freeform.sim.schedules import make_kernels
from freeform.sim.voxels import POISSON_SERIES_X


def _unit_quaternions(rng: np.random.Generator) -> np.ndarray:
    """(w, x, y, z) float64 [n, 4] with w >= 0: angles from 0 to just under π, dense around the series switch
    (tan(θ/4)² = 0.0256, θ ≈ 0.634 rad) and tiny angles down to 1e-7 rad."""
    angle_switch = 4 * np.arctan(np.sqrt(ATAN_SERIES_X2))
    angles = np.concatenate([
        np.geomspace(1e-7, 1e-2, 40),
        np.linspace(0.0, 3.1, 80),
        angle_switch * (1 + np.linspace(-1e-3, 1e-3, 21)),
    ])
    axes = rng.standard_normal((angles.size, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    xyzw = Rotation.from_rotvec(axes * angles[:, None]).as_quat()  # scipy: (x, y, z, w), w >= 0
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_rotation_vector_matches_scipy_on_both_sides_of_the_series_switch(precision):
    runtime.ensure("cpu")
    k = make_kernels(precision, "aos")
    real = np.float32 if precision == "f32" else np.float64
    q = _unit_quaternions(np.random.default_rng(0))
    q_in = runtime.from_numpy(q.astype(real), rows_as_vectors=True)
    rv = runtime.from_numpy(np.zeros((len(q), 3), real), rows_as_vectors=True)
    back = runtime.from_numpy(np.zeros((len(q), 4), real), rows_as_vectors=True)
    k.probe_rotations(q_in, rv, back)
    expect = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)).as_rotvec()
    got = runtime.to_numpy(rv).astype(np.float64)
    angle = np.linalg.norm(expect, axis=1)
    err = np.linalg.norm(got - expect, axis=1)
    if precision == "f32":
        # a few f32 ulps of the angle (atan2 form and series alike; no dead zone at tiny angles)
        assert np.all(err <= 4e-7 * np.maximum(angle, 1e-30) + 1e-12), err.max()
    else:
        # VX's own arithmetic: acos form, and below sin²(θ/2) = 2.4e-3 (θ < 0.098 rad) its shortcut
        # 2·xyz·sqrt((2 − 2w)/sin²), whose relative error is θ²/96 (6e-5 at θ = 0.078), plus the digits that
        # 1 − w = θ²/8 loses to double rounding of w (~4e-16/θ² relative): kept on purpose (spec)
        rel_bound = angle**2 / 90 + 1e-15 / np.maximum(angle, 1e-30) ** 2 + 1e-14
        assert np.all(err <= rel_bound * angle)
        small = angle < 0.09
        assert np.any(err[small] > 1e-3 * angle[small] ** 3)  # ... and it is there (f64 is VX, not exact)
    # FromRotationVector of the vector it got is scipy's quaternion of that vector (up to the quaternion's sign)
    b = runtime.to_numpy(back).astype(np.float64)
    xyzw = Rotation.from_rotvec(got).as_quat()
    want = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    tol = 3e-7 if precision == "f32" else 1e-14
    assert np.all(np.minimum(np.abs(b - want).max(axis=1), np.abs(b + want).max(axis=1)) < tol)


def test_poisson_series_coefficients_and_accuracy():
    """PB1..PB8 are C(−ν, k); the truncated series is within 5e-9 relative of (1+x)^(−ν) − 1 for |x| < 0.1
    (f32 rounding is 6e-8)."""
    cfg = SimConfig(materials=[Material(poisson=0.35), Material(poisson=0.1), Material(poisson=0.0)])
    t = material_table(cfg)
    pb = np.stack([t[MAT_COLUMNS.index(f"PB{k}")] for k in range(1, POISSON_SERIES_TERMS + 1)])  # [8, n_mat+1]
    x = np.linspace(-POISSON_SERIES_X, POISSON_SERIES_X, 401)
    for j, m in enumerate(cfg.materials, start=1):
        np.testing.assert_allclose(pb[:, j], binom(-m.poisson, np.arange(1, POISSON_SERIES_TERMS + 1)), rtol=1e-14)
        series = sum(pb[k, j] * x ** (k + 1) for k in range(POISSON_SERIES_TERMS))
        exact = (1 + x) ** (-m.poisson) - 1
        assert np.all(np.abs(series - exact) <= 5e-9 * np.abs(exact))
