"""Controllers for the control env: the masked Gaussian against torch.distributions over the entries that act, the
convolutional and MLP controllers' shapes and masks, and PPO training them on a ControlEnv where the passive cells'
entries never reach the loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.distributions import Normal, kl_divergence

from freeform.agents import PPO, ConvController, MLPActorCritic, MLPController, PPOConfig
from freeform.agents.distributions import MaskedDiagGaussian, from_spec
from freeform.agents.ppo import minibatch_loss, minibatch_samples
from freeform.envs.control import OBS_CHANNELS, ControlConfig, ControlEnv
from freeform.sim import SimConfig


def test_masked_gaussian_counts_only_the_masked_entries() -> None:
    """Truth: torch's Normal over the masked entries alone (a different count per row)."""
    g = torch.Generator().manual_seed(0)
    mean0, mean1, a = (torch.randn(5, 6, generator=g) for _ in range(3))
    s0, s1 = torch.randn(5, 6, generator=g) * 0.3, torch.randn(5, 6, generator=g) * 0.3
    mask = (torch.rand(5, 6, generator=g) < 0.5).float()
    mask[0] = 0.0  # a row with nothing that acts: 0 everywhere
    dist = MaskedDiagGaussian(6)
    p0, p1 = (mean0, s0, mask), (mean1, s1, mask)
    on = mask.bool()
    for row in range(5):
        k = on[row]
        torch.testing.assert_close(dist.log_prob(p1, a)[row], Normal(mean1[row, k], s1[row, k].exp()).log_prob(a[row, k]).sum())
        torch.testing.assert_close(dist.entropy(p1)[row], Normal(mean1[row, k], s1[row, k].exp()).entropy().sum())
        torch.testing.assert_close(dist.kl(p0, p1)[row], kl_divergence(Normal(mean0[row, k], s0[row, k].exp()),
                                                                       Normal(mean1[row, k], s1[row, k].exp())).sum())
    assert (dist.sample(p1, torch.randn(5, 6, generator=g))[~on] == 0).all()  # the ignored entries: 0
    assert from_spec(dist.spec()) == dist


def bodies() -> np.ndarray:
    """Two small bodies in a 4³ grid: a bar of muscle (2) and passive (1) voxels, and an L of muscle."""
    g = np.zeros((2, 4, 4, 4), np.uint8)
    g[0, 0:3, 0, 0] = [2, 1, 2]
    g[1, 0:2, 0, 0], g[1, 0, 1, 0] = 2, 2
    return g


def test_controllers_read_the_mask_from_the_actuated_channel() -> None:
    env = ControlEnv(bodies(), control=ControlConfig(burn_in=0.0, duration=0.05))
    obs = env.reset()
    torch.manual_seed(0)
    for net in (ConvController.for_env(env), MLPController.for_env(env, hidden=(16,))):
        mean, log_std, mask, value = net(obs)
        assert mean.shape == log_std.shape == mask.shape == (2, env.action_dim) and value.shape == (2,)
        torch.testing.assert_close(mask, env.action_mask.float())
        assert net.distribution == env.action_distribution
    assert env.mask_channel == OBS_CHANNELS.index("actuated")


def test_ppo_trains_a_controller_and_passive_cells_never_reach_the_loss(tmp_path) -> None:
    """One epoch of PPO on the control env: the weights move and σ is logged over the active entries. The loss's
    gradient is the same whatever actions are stored for cells that do not act, and whatever the policy's means are
    there (scrambled); it changes when an actuated cell's action does. A checkpoint rebuilds the controller."""
    env = ControlEnv(bodies(), sim=SimConfig(precision="f32"), control=ControlConfig(burn_in=0.0, duration=0.05))
    torch.manual_seed(0)
    ppo = PPO(env, ConvController.for_env(env, hidden=4), PPOConfig(rollout_steps=4, num_sgd_iter=1,
                                                                     sgd_minibatch_size=8, lr=1e-3, seed=0))
    start = ppo.flat.value.detach().clone()
    stats = ppo.train_epoch()
    assert (ppo.flat.value - start).abs().max() > 0 and np.isfinite(stats["action_std"])
    ro = ppo.rollout
    inactive = ~env.action_mask
    assert (ro.actions[:, inactive] == 0).all()  # the masked sample leaves them at 0

    def gradient(actions: torch.Tensor, old_means: torch.Tensor) -> torch.Tensor:
        params = (old_means.flatten(0, 1), ro.log_stds.flatten(0, 1), ro.params[2].flatten(0, 1))
        samples = minibatch_samples(actions.flatten(0, 1), params, ro.logprobs.flatten(), ro.values.flatten(),
                                    ro.returns.flatten())
        ppo.flat.zero_grad()
        loss, _ = minibatch_loss(ppo.policy, ppo.distribution, ppo.config, ro.obs.flatten(0, 1), samples,
                                 ro.advantages.flatten(), torch.tensor(0.5), torch.mean)
        loss.backward()
        return ppo.flat.grad.clone()

    reference = gradient(ro.actions, ro.means)
    scrambled, means = ro.actions.clone(), ro.means.clone()
    scrambled[:, inactive] = torch.randn_like(scrambled[:, inactive]) * 5
    means[:, inactive] = torch.randn_like(means[:, inactive]) * 5
    assert reference.abs().max() > 0
    torch.testing.assert_close(gradient(scrambled, means), reference)
    moved = ro.actions.clone()
    moved[:, env.action_mask] += 0.5
    assert (gradient(moved, ro.means) - reference).abs().max() > 1e-6  # (the check can tell)

    ppo.save(tmp_path / "controller.pt")
    loaded = PPO.load(tmp_path / "controller.pt", env)
    assert isinstance(loaded.policy, ConvController) and torch.equal(loaded.flat.value, ppo.flat.value)


def test_refusals_for_masked_actions_and_dict_observations() -> None:
    env = ControlEnv(bodies(), control=ControlConfig(burn_in=0.0, duration=0.05))
    with pytest.raises(ValueError, match="no head for a MaskedDiagGaussian"):
        MLPActorCritic.for_env(env)
    with pytest.raises(ValueError, match="obs_norm would rescale the observation channel"):
        PPO(env, ConvController.for_env(env), PPOConfig(rollout_steps=4, obs_norm=True))

    class DictEnv:
        observation_shape = {"a": (2,), "b": (3,)}
        action_dim = 1

    with pytest.raises(ValueError, match="observes a dict"):
        MLPActorCritic.for_env(DictEnv())
    for bad in (0, -2, 2.5, True):
        with pytest.raises(ValueError, match="positive int"):
            MaskedDiagGaussian(bad)


@pytest.mark.parametrize("bad", [dict(box=(2, 0, 1)), dict(mask_channel=20)])
def test_controller_refusals(bad: dict) -> None:
    kwargs = dict(channels=len(OBS_CHANNELS), box=(2, 2, 2), mask_channel=2) | bad
    with pytest.raises(ValueError, match="box|mask_channel"):
        ConvController(**kwargs)
