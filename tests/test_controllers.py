"""Controllers for the control env: the masked Gaussian against torch.distributions over the entries that act, the
convolutional and MLP controllers' shapes and masks, and PPO training them on a ControlEnv where the passive cells'
entries never reach the loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.distributions import Normal, kl_divergence

from freeform.agents import PPO, ConvController, MLPController, PPOConfig
from freeform.agents.distributions import MaskedDiagGaussian, from_spec
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


def test_ppo_trains_a_controller_and_passive_cells_never_reach_the_loss() -> None:
    """One epoch of PPO on the control env: the weights move, σ is logged over the active entries, and the loss's
    gradient does not depend on the actions stored for cells that do not act (changing them changes nothing)."""
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
    lp = ppo.distribution.log_prob(ro.params, ro.actions)
    scrambled = ro.actions.clone()
    scrambled[:, inactive] = torch.randn_like(scrambled[:, inactive]) * 5
    torch.testing.assert_close(ppo.distribution.log_prob(ro.params, scrambled), lp)


@pytest.mark.parametrize("bad", [dict(box=(2, 0, 1)), dict(mask_channel=20)])
def test_controller_refusals(bad: dict) -> None:
    kwargs = dict(channels=len(OBS_CHANNELS), box=(2, 2, 2), mask_channel=2) | bad
    with pytest.raises(ValueError, match="box|mask_channel"):
        ConvController(**kwargs)
