"""A body's response to its gait: each voxel's velocity at the actuation frequency over the last actuation period
(``control.response``, issue 56).

A feed-forward controller sees one instant of a body it never met. What per-body control fits is timing — when each
voxel moves in the gait's cycle — and that is what a body's response shows: over one actuation period T, each
voxel's velocity's Fourier coefficients at the frequency 1/T against the actuation clock θ = 2πt/T,

    a = (2/W) Σ_k v_k sin θ_k,    b = (2/W) Σ_k v_k cos θ_k     (the last W = T / step samples),

so that a velocity A·sin(θ + φ) reads a = A·cos φ, b = A·sin φ exactly: the amplitude and phase of how each voxel
moves with the clock, per axis. W samples one whole period, on which a constant drift and the higher harmonics up to
W/2 − 1 sum to zero. Until W samples are in (a fresh env before its burn-in is sensed), the sums run over the n < W
there are, scaled 2/n. A window instead of an exponential average: the average's ripple at 2/T is ≈ 8 % of A at
W = 20, the window's is none.
"""

from __future__ import annotations

import numpy as np

RESPONSE_CHANNELS = ("resp_x_sin", "resp_y_sin", "resp_z_sin", "resp_x_cos", "resp_y_cos", "resp_z_cos")
"""The response's channels (``a`` for x, y, z, then ``b``), appended after a control env's other channels."""


def response_window(temp_period: float, step: float) -> int:
    """Samples per actuation period, one every control period ``step``: ``temp_period / step`` (s / s), refused
    unless a whole number >= 4 (below 4 the second harmonic folds onto the first)."""
    ratio = temp_period / step
    window = round(ratio)
    if abs(ratio - window) > 1e-6 * max(1.0, ratio) or window < 4:
        raise ValueError(f"control.response samples one actuation period (sim.temp_period = {temp_period} s) every "
                         f"control period ({step} s): the period must be a whole number >= 4 of control periods, got "
                         f"{ratio:.6g} (set control.period to sim.temp_period / n, or control.response=false)")
    return window


class GaitResponse:
    """The last ``window`` samples of ``voxels`` voxels' velocities ``[V, 3]`` and the clock's phase θ (rad) at
    each: a ring buffer, whose :meth:`coefficients` are the response ``[V, 6]`` (module docstring)."""

    def __init__(self, voxels: int, window: int) -> None:
        self.window = int(window)
        self.velocity = np.zeros((self.window, int(voxels), 3))
        self.theta = np.zeros(self.window)
        self.count = 0
        """Samples added since the start (the ring's next slot is ``count mod window``)."""

    def add(self, velocity: np.ndarray, theta: float) -> None:
        """One sample: each voxel's velocity ``[V, 3]`` at clock phase ``theta``."""
        slot = self.count % self.window
        self.velocity[slot] = velocity
        self.theta[slot] = theta
        self.count += 1

    def coefficients(self) -> np.ndarray:
        """``[V, 6]``: (a_x, a_y, a_z, b_x, b_y, b_z) per voxel over the samples held (zeros before the first)."""
        n = min(self.count, self.window)
        if n == 0:
            return np.zeros((self.velocity.shape[1], 6))
        v, theta = self.velocity[:n], self.theta[:n]
        a = np.einsum("k,kvd->vd", np.sin(theta), v)
        b = np.einsum("k,kvd->vd", np.cos(theta), v)
        return (2.0 / n) * np.concatenate([a, b], 1)

    def state(self) -> tuple[np.ndarray, np.ndarray, int]:
        """A copy of the buffer, for :meth:`restore`."""
        return self.velocity.copy(), self.theta.copy(), self.count

    def restore(self, state: tuple[np.ndarray, np.ndarray, int]) -> None:
        velocity, theta, self.count = state
        self.velocity[:], self.theta[:] = velocity, theta


__all__ = ["RESPONSE_CHANNELS", "GaitResponse", "response_window"]
