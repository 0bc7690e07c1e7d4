"""Tests for bugs that a mutation check planted and the rest of the suite let through.

Each test states the bug it guards against and checks the code against a truth computed independently of it:
``torch.distributions`` for the KL, Adam's first-step formula for the KL penalty's gradient, the definition of a
standardised sample for per-minibatch advantage normalisation, and an uninterrupted run for resume.
"""

from __future__ import annotations

import copy
import random
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch.distributions import Normal, kl_divergence

import freeform.agents.ppo.losses as ppo_module
from freeform import train as train_mod
from freeform.agents import PPO, MLPActorCritic, PPOConfig
from freeform.agents.ppo import gaussian_kl, gaussian_log_prob
from freeform.config import AgentConfig, EnvConfig, TrainConfig, TrainerConfig

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py


class ReachEnv:
    """N points on a line, each to reach 0; obs = position [N, 1], action [N, 2] (the first component moves the
    point), reward = ``offset + scale_n · (−|position|)`` every step, episodes of ``horizon`` steps. The offset and
    the per-env scales make raw advantages far from standardised."""

    def __init__(self, num_envs: int = 8, horizon: int = 5, offset: float = 0.0) -> None:
        self.num_envs, self.horizon, self.offset = num_envs, horizon, offset
        self.observation_shape, self.action_dim, self.device = (1,), 2, torch.device("cpu")
        self.scale = torch.linspace(1.0, 30.0, num_envs)
        self.generator = torch.Generator().manual_seed(0)
        self.pos = torch.zeros(num_envs, 1)
        self.t = 0

    def reset(self, seed: int | None = None) -> torch.Tensor:
        if seed is not None:
            self.generator.manual_seed(seed)
        self.pos = torch.rand(self.num_envs, 1, generator=self.generator) * 4 - 2
        self.t = 0
        return self.pos.clone()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        self.pos = self.pos + 0.2 * actions[:, :1].clamp(-1, 1)
        self.t += 1
        reward = self.offset - self.scale * self.pos.abs().squeeze(1)
        done = torch.full((self.num_envs,), self.t == self.horizon)
        if self.t == self.horizon:
            self.reset()
        return self.pos.clone(), reward, done, {}


def reach_ppo(**overrides: Any) -> PPO:
    cfg = dict(rollout_steps=6, num_sgd_iter=1, sgd_minibatch_size=48, lr=1e-3, seed=2)  # B = 6 · 8 = 48
    cfg.update(overrides)
    torch.manual_seed(0)  # the network's init draws from the global RNG (restored by keep_global_rng)
    return PPO(
        ReachEnv(offset=cfg.pop("reward_offset", 0.0)), MLPActorCritic(1, 2, hidden=(16,)), PPOConfig(**cfg)
    )


def perturb_old_policy(ppo: PPO) -> None:
    """Make the stored π_old differ from π, asymmetrically: means shifted by +1.0 and −0.5 per dim, σ_old = 0.6·σ
    on dim 0 and 1.5·σ on dim 1 (KL(π_old ‖ π) ≠ KL(π ‖ π_old)); logprobs recomputed under the new π_old.

    With the untrained ``MLPActorCritic`` (σ = 1), ∂/∂log σ₀ of KL(π_old ‖ π) = 1 − (σ_old² + Δμ²)/σ² = −0.36 but
    of KL(π ‖ π_old) = σ²/σ_old² − 1 = +1.78: opposite signs."""
    ro = ppo.rollout
    ro.means += torch.tensor([1.0, -0.5])
    ro.log_stds += torch.log(torch.tensor([0.6, 1.5]))
    ro.logprobs.copy_(gaussian_log_prob(ro.actions, ro.means, ro.log_stds))


def test_gaussian_kl_direction_matches_torch_distributions() -> None:
    """Bug: ``gaussian_kl`` computing KL(N1 ‖ N0) for arguments (N0, N1). Truth: ``torch.distributions.kl_divergence``
    of Normals with clearly different σ (where the two directions differ by far more than the tolerance)."""
    g = torch.Generator().manual_seed(4)
    m0, m1 = torch.randn(6, 3, generator=g), torch.randn(6, 3, generator=g)
    s0, s1 = torch.randn(6, 3, generator=g) * 0.3 - 0.7, torch.randn(6, 3, generator=g) * 0.3 + 0.7
    forward = kl_divergence(Normal(m0, s0.exp()), Normal(m1, s1.exp())).sum(-1)
    backward = kl_divergence(Normal(m1, s1.exp()), Normal(m0, s0.exp())).sum(-1)
    assert (forward - backward).abs().min() > 0.1  # the check below can tell the directions apart
    torch.testing.assert_close(gaussian_kl(m0, s0, m1, s1), forward)


def test_reported_kl_is_kl_of_old_policy_to_new() -> None:
    """Bug: the update's KL (loss and ``approx_kl``) taken as KL(π ‖ π_old) instead of KL(π_old ‖ π). At the first
    step of an epoch π = π_old and both are 0, so the stored π_old is perturbed first. With one pass and one
    minibatch holding the whole batch, ``approx_kl`` is the KL before the step; truth: the mean over the batch of
    ``kl_divergence(Normal(old), Normal(π)).sum(-1)`` with π evaluated independently on a copy of the policy."""
    ppo = reach_ppo()
    ppo.collect()
    perturb_old_policy(ppo)
    ro = ppo.rollout
    before = copy.deepcopy(ppo.policy)
    with torch.no_grad():
        mean, log_std, _ = before(ro.obs.reshape(48, 1))
    old = Normal(ro.means.reshape(48, 2), ro.log_stds.reshape(48, 2).exp())
    new = Normal(mean, log_std.exp())
    expected = kl_divergence(old, new).sum(-1).mean().item()
    reversed_kl = kl_divergence(new, old).sum(-1).mean().item()
    assert abs(expected - reversed_kl) > 0.1 * expected  # the perturbation tells the two directions apart

    stats = ppo.update()
    assert stats["approx_kl"] == pytest.approx(expected, rel=1e-5), (
        stats["approx_kl"],
        expected,
        reversed_kl,
    )


def test_kl_penalty_gradient_is_that_of_kl_old_to_new() -> None:
    """Bug: the KL(π_old ‖ π) penalty in the *loss* reversed (even where the reported ``approx_kl`` is right).

    The loss is reduced to the penalty alone: advantages 0 (policy loss 0, no gradient), ``vf_loss_coeff = 0``,
    ``entropy_coeff = 0``; π_old perturbed as above. One pass, one minibatch = one Adam step from a fresh optimizer,
    whose update is exactly Δθ = −lr · g / (|g| + eps) (m̂ = g, v̂ = g²; spec: Adam with torch defaults). Truth: g
    = ∇θ β·mean KL(π_old ‖ π) from ``torch.distributions`` on a copy of the policy. The reversed KL's gradient
    wrt log σ has the opposite sign on dim 0 (see ``perturb_old_policy``), so its step differs."""
    lr, beta = 1e-3, 1.0
    ppo = reach_ppo(lr=lr, kl_coeff=beta, vf_loss_coeff=0.0, advantage_norm="none")
    ppo.collect()
    perturb_old_policy(ppo)
    ro = ppo.rollout
    ro.advantages.zero_()

    reference = copy.deepcopy(ppo.policy)
    mean, log_std, _ = reference(ro.obs.reshape(48, 1))
    old = Normal(ro.means.reshape(48, 2), ro.log_stds.reshape(48, 2).exp())
    kl = beta * kl_divergence(old, Normal(mean, log_std.exp())).sum(-1).mean()
    kl.backward()
    eps = 1e-8  # torch.optim.Adam's default
    expected = {
        name: torch.zeros_like(p) if p.grad is None else -lr * p.grad / (p.grad.abs() + eps)
        for name, p in reference.named_parameters()
    }
    before = {name: p.detach().clone() for name, p in ppo.policy.named_parameters()}

    ppo.update()
    for name, p in ppo.policy.named_parameters():
        step = p.detach() - before[name]
        torch.testing.assert_close(
            step,
            expected[name],
            atol=lr * 1e-3,
            rtol=1e-3,
            msg=lambda m, name=name: f"Adam step of {name}: {m}",
        )


def test_minibatch_advantage_norm_standardises_each_minibatch() -> None:
    """Bug: ``advantage_norm="minibatch"`` standardising each minibatch with the whole batch's mean and std (or
    not at all). Truth: by definition every minibatch's advantages, as the loss uses them, have mean 0 and
    population std 1 (RLlib's ``standardize``). They are observed where the loss receives them: the advantages
    argument of ``clipped_surrogate``. Raw advantages have a large offset and per-env scales (rewards 500 −
    (1…30)·|x|), far from standardised over the batch or any minibatch."""
    ppo = reach_ppo(advantage_norm="minibatch", num_sgd_iter=3, sgd_minibatch_size=12, reward_offset=500.0)
    ppo.collect()
    raw = ppo.rollout.advantages.reshape(-1)
    assert raw.mean().abs() > 50 and raw.std() > 5  # far from standardised

    seen: list[torch.Tensor] = []
    surrogate = ppo_module.clipped_surrogate

    def recording(ratio: torch.Tensor, advantages: torch.Tensor, clip_param: float) -> torch.Tensor:
        seen.append(advantages.detach().clone())
        return surrogate(ratio, advantages, clip_param)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ppo_module, "clipped_surrogate", recording)
        ppo.update()

    assert len(seen) == 3 * (48 // 12) and all(a.shape == (12,) for a in seen)
    for i, adv in enumerate(seen):
        assert abs(adv.mean().item()) < 1e-5, (i, adv.mean().item())
        assert adv.std(correction=0).item() == pytest.approx(1.0, abs=1e-5), (i, adv.std(correction=0).item())


def tiny_train_config(epochs: int, resume: str | None = None) -> TrainConfig:
    """The tiny run of tests/test_train.py (ρ = 6, 4 environments, T = 5) as dataclasses, no records or renders."""
    return TrainConfig(
        seed=5,
        env=EnvConfig(num_envs=4, resolution=6, steps=5),
        agent=AgentConfig(hidden=16, num_sgd_iter=2, sgd_minibatch_size=8),
        trainer=TrainerConfig(
            epochs=epochs,
            device="cpu",
            checkpoint_every=0,
            resume=resume,
            record_designs=False,
            render_every=0,
            print_every=0,
            progress=False,
        ),
    )


def test_resume_restores_the_global_rngs_a_callback_draws_from(tmp_path: Path) -> None:
    """Bug: resume not restoring the global RNGs (torch, numpy, python ``random``) from the checkpoint. The run
    itself draws nothing from them after building (PPO and the env have their own generators), so only code that
    uses them — a per-epoch callback, say — sees the bug: after a resume it gets the draws of a freshly seeded run.
    Truth: the uninterrupted run. A callback draws from all three RNGs every epoch (callbacks run before the epoch's
    checkpoint, so the checkpoint holds the state after the draws); 2 epochs straight = 1 epoch + resume 1."""

    def drawing(draws: list[tuple[list[float], list[float], float]]) -> train_mod.EpochCallback:
        def callback(ctx: train_mod.EpochContext) -> None:
            draws.append((torch.rand(3).tolist(), np.random.rand(3).tolist(), random.random()))

        return callback

    straight: list[tuple[list[float], list[float], float]] = []
    train_mod.train(tiny_train_config(epochs=2), tmp_path / "straight", callbacks=[drawing(straight)])
    split: list[tuple[list[float], list[float], float]] = []
    train_mod.train(tiny_train_config(epochs=1), tmp_path / "split", callbacks=[drawing(split)])
    train_mod.train(
        tiny_train_config(epochs=2, resume=str(tmp_path / "split")),
        tmp_path / "split",
        callbacks=[drawing(split)],
    )

    assert len(straight) == len(split) == 2
    for rng in range(3):  # the second epoch's draws differ from the first's, so a re-seeded RNG would show
        assert straight[0][rng] != straight[1][rng]
    assert split[0] == straight[0]
    for name, got, want in zip(("torch", "numpy", "python"), split[1], straight[1], strict=True):
        assert got == want, f"{name} global RNG after resume: {got} != {want} (uninterrupted run)"
