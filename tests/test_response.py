"""A body's response to its gait (``control.response``, freeform/envs/response.py): the window's Fourier
coefficients against a sinusoid's amplitude and phase, the env's response channels against the same sums over
its own velocity and clock channels, sensed from the burn-in on, and teachers that never saw the channels."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from freeform.envs.control import RESIDUAL_CHANNELS, ControlConfig, ControlEnv
from freeform.envs.response import RESPONSE_CHANNELS, GaitResponse, response_window
from freeform.sim import SimConfig


def test_the_window_reads_a_sinusoids_amplitude_and_phase_whatever_the_drift_and_harmonics():
    """v = A·sin(θ + φ) + c + d·sin(2θ + ψ) + e·cos(5θ) per axis, sampled 20 times a period for 1.6 periods (the
    ring wraps, and starts mid-period): the coefficients are (A cos φ, A sin φ), exactly."""
    window, rng = 20, np.random.default_rng(0)
    amplitude, phase = rng.uniform(0.1, 2.0, (7, 3)), rng.uniform(-math.pi, math.pi, (7, 3))
    drift, second, psi, fifth = (rng.normal(size=(7, 3)) for _ in range(4))
    response = GaitResponse(7, window)
    for k in range(32):
        theta = 2 * math.pi * (k + 3) / window
        v = (amplitude * np.sin(theta + phase) + drift + second * np.sin(2 * theta + psi)
             + fifth * np.cos(5 * theta))
        response.add(v, theta)
    coefficients = response.coefficients()
    np.testing.assert_allclose(coefficients[:, :3], amplitude * np.cos(phase), atol=1e-12)
    np.testing.assert_allclose(coefficients[:, 3:], amplitude * np.sin(phase), atol=1e-12)
    assert np.array_equal(GaitResponse(7, window).coefficients(), np.zeros((7, 6)))  # nothing sensed yet


def test_a_period_that_is_not_a_whole_number_of_steps_is_refused():
    assert response_window(0.25, 0.0125) == 20
    with pytest.raises(ValueError, match=r"a whole number >= 4 of control periods, got 3\.2"):
        response_window(0.25, 0.078125)
    with pytest.raises(ValueError, match=r"got 2 "):
        response_window(0.25, 0.125)


def _body() -> np.ndarray:
    """A 3-voxel bar: two muscles of opposite phase (materials 2 and 3) and a passive voxel (1) between them."""
    g = np.zeros((1, 4, 4, 4), np.uint8)
    g[0, 0, 0, 0], g[0, 1, 0, 0], g[0, 2, 0, 0] = 2, 1, 3
    return g


def test_the_response_channels_sum_the_env_velocity_and_clock_channels_from_the_burn_in_on():
    """An env with the response and a burn-in of one actuation period (residual: the body plays its gait) starts
    with what a twin without burn-in, run on zero actions through that period, senses: each response channel
    (2/W)·Σ vel·clock over the W observations, the twin's own channels."""
    sim, period = SimConfig(precision="f64"), 0.0125
    window = response_window(sim.temp_period, period)
    control = ControlConfig(period=period, duration=2 * window * period, residual=True, response=True)
    env = ControlEnv(_body(), sim=sim, control=ControlConfig(**{**vars(control), "burn_in": window * period}))
    assert env.channels == (*RESIDUAL_CHANNELS, *RESPONSE_CHANNELS)
    first = env.reset()
    twin = ControlEnv(_body(), sim=sim, control=ControlConfig(**{**vars(control), "burn_in": 0.0}))
    c = {name: i for i, name in enumerate(twin.channels)}
    obs, seen = twin.reset(), []
    for _ in range(window):
        obs, *_ = twin.step(torch.zeros(1, twin.action_dim))
        seen.append(obs[0].double())
    seen = torch.stack(seen)  # [W, C, Bx, By, Bz]: the observations at t = step … W·step
    for axis in "xyz":
        v = seen[:, c[f"vel_{axis}"]]
        for clock in ("sin", "cos"):
            want = 2.0 / window * (v * seen[:, c[f"clock_{clock}"]]).sum(0)
            if axis == "x":  # (the bar moves along x in its gait: the sums are not trivially zero)
                assert want.abs().max() > 1e-3
            torch.testing.assert_close(obs[0, c[f"resp_{axis}_{clock}"]].double(), want, atol=1e-5, rtol=1e-4)
            torch.testing.assert_close(first[0, c[f"resp_{axis}_{clock}"]].double(), want, atol=1e-5, rtol=1e-4)
    # the other channels are the env's without the response: the same gait, bit for bit after the same burn-in
    plain = ControlEnv(_body(), sim=sim, control=ControlConfig(**{**vars(control), "response": False,
                                                                  "burn_in": window * period}))
    assert torch.equal(plain.reset(), first[:, : len(RESIDUAL_CHANNELS)])
    env.reset()  # (a later episode starts from the settled state and its response, not from an empty window)
    torch.testing.assert_close(env.reset(), first)


def test_a_stroke_senses_every_control_period_it_holds():
    """Strokes of 5 periods (a decision every 5 control periods): after 4 zero strokes the response is a twin's
    that decides every period, after 20 zero steps — both sampled every period, as their clocks read."""
    sim = SimConfig(precision="f64")
    control = ControlConfig(burn_in=0.0, duration=0.5, residual=True, response=True)
    twin = ControlEnv(_body(), sim=sim, control=control)
    strokes = ControlEnv(_body(), sim=sim, control=ControlConfig(**{**vars(control), "stroke_periods": 5}))
    twin.reset(), strokes.reset()
    for _ in range(20):
        obs, *_ = twin.step(torch.zeros(1, twin.action_dim))
    for _ in range(4):
        held, *_ = strokes.step(torch.zeros(1, strokes.action_dim))
    assert held[0, -6:].abs().max() > 1e-3
    torch.testing.assert_close(held[:, -6:], obs[:, -6:], atol=1e-6, rtol=1e-5)


def test_teachers_read_the_channels_they_were_built_for():
    """A bank built for the residual channels gives, on an observation with the response appended, what it gives
    on that observation without it; an observation with fewer channels than it reads is refused."""
    from freeform.agents.distill.teachers import TEACHER, TeacherBank
    from freeform.agents.networks.controllers import build_controller

    sim = SimConfig()
    control = ControlConfig(duration=0.05, residual=True)
    plain = ControlEnv(np.concatenate([_body()] * 2), sim=sim, control=control)
    seeing = ControlEnv(np.concatenate([_body()] * 2), sim=sim,
                        control=ControlConfig(**{**vars(control), "response": True}))
    torch.manual_seed(0)
    bank = TeacherBank.from_template(build_controller("attention", plain, 16), 2)
    obs = seeing.reset()
    obs[:, len(RESIDUAL_CHANNELS):] = torch.randn(2, len(RESPONSE_CHANNELS), *seeing.box)  # (whatever they hold)
    teacher = torch.tensor([1, 0])
    with torch.no_grad():
        wide = bank({TEACHER: teacher, "policy": obs})
        narrow = bank({TEACHER: teacher, "policy": obs[:, : len(RESIDUAL_CHANNELS)].clone()})
        for a, b in zip(wide, narrow, strict=True):
            assert torch.equal(a, b)
        with pytest.raises(ValueError, match=r"the teachers read 17 observation channels and this env gives 16"):
            bank({TEACHER: teacher, "policy": obs[:, :16]})
