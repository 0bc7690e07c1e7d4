"""Controllers for the control env: the masked Gaussian against torch.distributions over the entries that act, the
convolutional and MLP controllers' shapes and masks, and PPO training them on a ControlEnv where the passive cells'
entries never reach the loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal, kl_divergence

from freeform.agents import PPO, ConvController, MLPActorCritic, MLPController, PPOConfig
from freeform.agents.controller_file import read_controller, save_controller
from freeform.agents.networks import rebuild
from freeform.agents.networks.controller_heads import WAVE_KINDS, HandSetWave
from freeform.agents.networks.controllers import (
    CONTROLLERS,
    PrivilegedCritic,
    build_controller,
    controller_step,
    with_wave_gain,
)
from freeform.agents.networks.recurrent import RecurrentPolicy
from freeform.agents.ppo import minibatch_loss, minibatch_samples
from freeform.distributions import MaskedDiagGaussian, from_spec
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


# ------------------------------------------------------------------ controllers with a view of the whole body

BOX_FREE = ("context", "attention", "context_gru", "attention_gru", "attention_hyper")  # the kinds whose padding changes nothing


def run(net: torch.nn.Module, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """One step of any controller from its episode's start (a recurrent one from its initial state)."""
    return controller_step(net, obs)[0]


def two_boxes() -> tuple[ControlEnv, ControlEnv]:
    """The bar alone (box 3 × 1 × 1) and the bar beside a larger body, a 3 × 2 × 2 block of muscle with a passive
    voxel (box 3 × 2 × 2); a short settle so that velocities and strains are not 0."""
    big = np.zeros((4, 4, 4), np.uint8)
    big[0:3, 0:2, 0:2], big[1, 1, 1] = 3, 1
    control = ControlConfig(burn_in=0.01, duration=0.05)
    return (ControlEnv(bodies()[:1], control=control), ControlEnv(np.stack([bodies()[0], big]), control=control))


@pytest.fixture(scope="module")
def envs_and_obs() -> tuple[ControlEnv, ControlEnv, torch.Tensor, torch.Tensor]:
    small, large = two_boxes()
    return small, large, small.reset(), large.reset()


@pytest.mark.parametrize("kind", list(CONTROLLERS))
def test_every_controller_gives_a_command_per_cell_and_the_env_mask_on_bodies_of_different_boxes(kind, envs_and_obs):
    for env, obs in (envs_and_obs[0], envs_and_obs[2]), (envs_and_obs[1], envs_and_obs[3]):
        torch.manual_seed(0)
        net = build_controller(kind, env, hidden=8 if kind != "mlp" else 16, log_std=-0.5)
        mean, log_std, mask, value = run(net, obs)
        assert mean.shape == log_std.shape == mask.shape == (env.num_envs, env.action_dim)
        assert value.shape == (env.num_envs,) and torch.isfinite(value).all()
        torch.testing.assert_close(mask, env.action_mask.float())
        assert net.distribution == env.action_distribution
        torch.testing.assert_close(log_std, torch.full_like(mean, -0.5))
        assert 0 < mean.abs().max() < 0.2  # the head starts near 0: an untrained controller leaves a body near rest
        if kind in BOX_FREE:  # (no command for a cell without a voxel)
            assert (mean[obs[:, env.filled_channel].flatten(1) == 0] == 0).all()


def test_padding_changes_nothing_for_the_masked_controllers_and_changes_the_conv_controllers(envs_and_obs):
    """Truth: the bar alone in its own box 3 × 1 × 1. The same observation padded into the 3 × 2 × 2 box beside
    the larger body (as the env pads it: at the corner, zeros around) must give the same commands on its cells and
    the same value. ConvController's biases leak into the padding, so it fails this (the check can tell)."""
    small, large, obs_small, obs_large = envs_and_obs
    cells = small.box
    torch.testing.assert_close(obs_large[0, :, : cells[0], : cells[1], : cells[2]], obs_small[0])  # (the env's padding)
    batch = obs_large.clone()
    for kind, head in (*((k, "direct") for k in BOX_FREE), *((k, "rhythm") for k in BOX_FREE), ("conv", "direct")):
        torch.manual_seed(1)
        net = build_controller(kind, large, hidden=8, head=head)
        with torch.no_grad():
            mean_big, _, _, value_big = run(net, batch)
            mean_alone, _, _, value_alone = run(net, obs_small)  # (the same weights on another box)
        on_its_cells = mean_big[0].view(large.box)[: cells[0], : cells[1], : cells[2]].reshape(-1)
        if kind == "conv":
            assert (on_its_cells - mean_alone[0]).abs().max() > 1e-5 or (value_big[0] - value_alone[0]).abs() > 1e-5
            continue
        torch.testing.assert_close(on_its_cells, mean_alone[0], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(value_big[0], value_alone[0], rtol=1e-5, atol=1e-6)
        assert (mean_alone[0] != 0).any()


@pytest.mark.parametrize("kind", BOX_FREE)
def test_a_rhythm_head_commands_its_amplitudes_on_the_actuation_clock(kind, envs_and_obs):
    """Truth: the observation's own clock channels. With the head's weights 0 and its biases (u, v, w), every filled
    cell's mean command is u·sin(2πt/T) + v·cos(2πt/T) + w, and an empty cell's is 0."""
    _, env, _, obs = envs_and_obs
    net = build_controller(kind, env, hidden=8, head="rhythm")
    with torch.no_grad():
        net.actor.weight.zero_()
        net.actor.bias.copy_(torch.tensor([0.7, -0.4, 0.1]))
        mean = run(net, obs)[0]
    clock_sin, clock_cos = (obs[:, env.channels.index(c)].flatten(1) for c in ("clock_sin", "clock_cos"))
    filled = obs[:, env.filled_channel].flatten(1)
    assert 0 < clock_sin.abs().max() and 0 < clock_cos.abs().max()  # (the clock is not at a zero of either)
    torch.testing.assert_close(mean, (0.7 * clock_sin - 0.4 * clock_cos + 0.1) * filled)
    with pytest.raises(ValueError, match="head='rhythm' is for the controllers"):
        build_controller("conv", env, hidden=8, head="rhythm")
    with pytest.raises(ValueError, match="head must be one of"):
        build_controller(kind, env, hidden=8, head="sine")


@pytest.mark.parametrize("kind", BOX_FREE)
def test_the_masked_distribution_ignores_the_unactuated_cells(kind, envs_and_obs):
    """The log-probability and entropy of the controller's distribution do not move when the actions of cells that
    do not act (a passive voxel, empty cells) are scrambled; they do when an actuated cell's action moves."""
    _, env, _, obs = envs_and_obs
    torch.manual_seed(2)
    net = build_controller(kind, env, hidden=8)
    params = run(net, obs)[:3]
    actions = torch.randn(env.num_envs, env.action_dim)
    scrambled, moved = actions.clone(), actions.clone()
    scrambled[~env.action_mask] = torch.randn(int((~env.action_mask).sum())) * 10
    moved[env.action_mask] += 0.5
    dist = net.distribution
    torch.testing.assert_close(dist.log_prob(params, scrambled), dist.log_prob(params, actions))
    assert (dist.log_prob(params, moved) - dist.log_prob(params, actions)).abs().min() > 1e-4


def test_a_controller_built_for_one_box_runs_on_another_and_reads_back_for_it(tmp_path, envs_and_obs):
    """Weights of a controller built for the 3 × 1 × 1 box run the 3 × 2 × 2 one (read back by read_controller
    for that box: the same outputs as the weights loaded by hand); the MLP is refused with the reason."""
    small, large, _, obs = envs_and_obs
    for kind in (*BOX_FREE, "conv"):
        torch.manual_seed(3)
        net = build_controller(kind, small, hidden=8)
        save_controller(tmp_path / f"{kind}.pt", net, ControlConfig(burn_in=0.01, duration=0.05), SimConfig())
        saved = read_controller(tmp_path / f"{kind}.pt", box=large.box)
        assert saved.kind == kind and saved.controller.box == large.box and saved.control.duration == 0.05
        assert saved.sim == SimConfig()
        by_hand = rebuild(CONTROLLERS[kind], {**net.init_kwargs, "box": large.box})
        by_hand.load_state_dict(net.state_dict())
        with torch.no_grad():
            for a, b in zip(run(saved.controller, obs), run(by_hand, obs), strict=True):
                torch.testing.assert_close(a, b, rtol=0, atol=0)
    mlp = build_controller("mlp", small, hidden=8)
    save_controller(tmp_path / "mlp.pt", mlp, ControlConfig())
    assert read_controller(tmp_path / "mlp.pt", box=small.box).kind == "mlp"  # its own box: fine
    with pytest.raises(ValueError, match=r"'mlp' controller learnt each cell of its box \(3, 1, 1\) apart.*\(3, 2, 2\)"):
        read_controller(tmp_path / "mlp.pt", box=large.box)


@pytest.mark.parametrize("kind", BOX_FREE)
def test_ppo_trains_the_masked_controllers(kind, tmp_path) -> None:
    """One PPO epoch moves every weight the loss reaches (actor head, trunk, critic, σ; the memory of
    ``attention_gru`` after its silent recall has moved, and ``attention_hyper``'s body code after its silent
    generator, an epoch later) and a run's checkpoint of it reads back as a controller."""
    env = ControlEnv(bodies(), sim=SimConfig(precision="f32"), control=ControlConfig(burn_in=0.0, duration=0.05))
    torch.manual_seed(0)
    net = build_controller(kind, env, hidden=8)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    ppo = PPO(env, net, PPOConfig(rollout_steps=4, num_sgd_iter=1, sgd_minibatch_size=8, lr=1e-3, seed=0))
    assert np.isfinite(ppo.train_epoch()["action_std"])
    if kind in ("attention_gru", "attention_hyper"):
        ppo.train_epoch()
    still = [k for k, v in net.state_dict().items() if torch.equal(v, before[k])]
    assert still == []
    ppo.save(tmp_path / "ppo.pt")
    (tmp_path / "args.json").write_text('{"burn_in": 0.0}')  # (lab/control.py's older layout)
    saved = read_controller(tmp_path / "ppo.pt")
    assert saved.kind == kind and all(torch.equal(v, net.state_dict()[k]) for k, v in saved.controller.state_dict().items())
    again = PPO.load(tmp_path / "ppo.pt", env)  # (PPO's own loader builds every registered controller)
    assert type(again.policy) is type(net) and all(torch.equal(v, net.state_dict()[k])
                                                   for k, v in again.policy.state_dict().items())


@pytest.mark.parametrize(("kind", "now", "before"), [
    ("conv", "freeform.agents.networks.controllers:ConvController", "freeform.agents.networks:ConvController"),
    ("conv", "freeform.agents.networks.controllers:ConvController", "freeform.agents.controllers:ConvController"),
    ("attention", "freeform.agents.networks.attention_controllers:VoxelAttentionController",
     "freeform.agents.controllers:VoxelAttentionController"),
    ("attention", "freeform.agents.networks.attention_controllers:VoxelAttentionController",
     "freeform.agents.attention_controllers:VoxelAttentionController")])
def test_ppo_loads_a_checkpoint_naming_the_controllers_old_module(tmp_path, kind, now, before) -> None:
    """Checkpoints written before a controller moved name its old module (the conv controller's agents/networks.py,
    the attention controller's agents/controllers.py, and every controller's module before agents/ was laid out by
    kind, agents/controllers.py and agents/attention_controllers.py); they still load."""
    from freeform.checkpoint import load_checkpoint, save_checkpoint

    env = ControlEnv(bodies(), sim=SimConfig(precision="f32"), control=ControlConfig(burn_in=0.0, duration=0.05))
    ppo = PPO(env, build_controller(kind, env, hidden=4), PPOConfig(rollout_steps=4, sgd_minibatch_size=8, seed=0))
    ppo.save(tmp_path / "ppo.pt")
    payload = load_checkpoint(tmp_path / "ppo.pt")
    assert payload["policy_class"] == now
    payload["policy_class"] = before
    save_checkpoint(tmp_path / "old.pt", payload)
    assert type(PPO.load(tmp_path / "old.pt", env).policy) is CONTROLLERS[kind]


def test_the_registry_names_reach_the_config() -> None:
    from freeform.config import ControlRunConfig

    for kind in CONTROLLERS:
        ControlRunConfig(controller=kind).validate()
    from benchmarks.bench_controllers import WIDTHS

    assert set(WIDTHS) == set(CONTROLLERS)  # (make bench times every kind: a new one needs its width)
    with pytest.raises(ValueError, match=r"control.controller.*'conv', 'mlp', 'context', 'attention'"):
        ControlRunConfig(controller="unet").validate()
    with pytest.raises(ValueError, match="controller kind must be one of"):
        build_controller("unet", None)
    ControlRunConfig(controller="context", head="wave", stroke_periods=10).validate()
    ControlRunConfig(controller="attention", head="wave", stroke_periods=10).validate()
    for bad, match in ((dict(controller="mlp", head="wave", stroke_periods=10), "control.head"),
                       (dict(controller="context", head="wave"), "control.head.*stroke_periods >= 1"),
                       (dict(controller="context", head="wave", stroke_periods=10, wave_k=float("nan")),
                        "control.wave_k"),
                       (dict(controller="context", head="wave", stroke_periods=10, wave_amplitude=0.0),
                        "control.wave_amplitude"),
                       (dict(controller="context", head="wave", stroke_periods=10, wave_gain=-0.5),
                        "control.wave_gain.*a finite gain >= 0")):
        with pytest.raises(ValueError, match=match):
            ControlRunConfig(**bad).validate()


@pytest.mark.parametrize("kind", BOX_FREE)
def test_a_stroke_head_gives_each_cell_a_and_b_padding_changes_nothing(kind):
    """An env of strokes (``stroke_periods``): the head's mean is every filled cell's a, then its b (the head's
    two biases where its weights are 0), the mask the actuated cells twice; the bar alone and padded beside the larger
    body gets the same (a, b); a direct head on this env, or a stroke head on a period env, is refused."""
    small, large = (replace_control(env, stroke_periods=2) for env in two_boxes())
    obs_small, obs_large = small.reset(), large.reset()
    net = build_controller(kind, large, hidden=8, head="stroke")
    with torch.no_grad():
        mean, _, mask, _ = run(net, obs_large)
        net.actor.weight.zero_()
        net.actor.bias.copy_(torch.tensor([0.3, -0.6]))
        constant = run(net, obs_large)[0]
        alone = run(net, obs_small)[0]
    cells = math.prod(large.box)
    assert mean.shape == mask.shape == (2, 2 * cells) and net.distribution == large.action_distribution
    torch.testing.assert_close(mask, large.action_mask.float())
    filled = obs_large[:, large.filled_channel].flatten(1)
    torch.testing.assert_close(constant, torch.cat([0.3 * filled, -0.6 * filled], 1))
    a, b = constant[0, :cells].view(large.box), constant[0, cells:].view(large.box)
    ends = small.box
    torch.testing.assert_close(torch.cat([a[: ends[0], : ends[1], : ends[2]].reshape(-1),
                                          b[: ends[0], : ends[1], : ends[2]].reshape(-1)]), alone[0])
    with pytest.raises(ValueError, match=r"head must be one of \['stroke', 'wave'\] exactly when control.stroke_periods >= 1"):
        build_controller(kind, large, hidden=8)
    with pytest.raises(ValueError, match="exactly when control.stroke_periods >= 1"):
        build_controller(kind, two_boxes()[1], hidden=8, head="stroke")


@pytest.mark.parametrize(("residual", "headings"), [(True, "fixed"), (False, "fixed"), (True, "random")])
@pytest.mark.parametrize("kind", WAVE_KINDS)
def test_a_wave_head_plays_a_travelling_wave_and_padding_changes_nothing(kind, residual, headings, tmp_path):
    """Truth: what the stroke env plays, (1 + a)·sin θ + b·cos θ under residual control (a·sin θ + b·cos θ without),
    θ = 2π(t/T + φ) each voxel's own phase (φ its material's, read from the sim's materials), equals
    (A + α)·sin(2πt/T − k·x − ψ) + ca·sin θ + cb·cos θ at every t for the head whose per-cell outputs are the
    constants (α, ψ, ca, cb): first the untrained wave (all 0, k = (k, 0, 0) and A from the hand-set wave), then a wave
    vector along y set through its layer's bias with every per-cell term set. With random headings both vectors are
    in the heading's frame: the world's k is turned by each body's heading (x along it), so the wave travels where
    the body is sent. Padding changes nothing with the wave vector's weights scaled up (a leak into the pooled
    features would move k); a controller.pt gives the same means; the conv controller and a period env are
    refused."""
    small, large = (replace_control(env, stroke_periods=2, residual=residual, headings=headings)
                    for env in two_boxes())
    obs_small, obs_large = small.reset(), large.reset()
    torch.manual_seed(0)
    net = build_controller(kind, large, hidden=8, head="wave", wave=HandSetWave(k=0.8, amplitude=1.4))
    with torch.no_grad():
        net.wave_k.weight.mul_(100.0)
        mean_large, _, mask, _ = run(net, obs_large)
        alone = run(net, obs_small)[0]
    cells = math.prod(large.box)
    assert mean_large.shape == mask.shape == (2, 2 * cells) and net.distribution == large.action_distribution
    a, b = mean_large[0, :cells].view(large.box), mean_large[0, cells:].view(large.box)
    ends = small.box
    torch.testing.assert_close(torch.cat([a[: ends[0], : ends[1], : ends[2]].reshape(-1),
                                          b[: ends[0], : ends[1], : ends[2]].reshape(-1)]), alone[0])
    save_controller(tmp_path / "controller.pt", net, large.control, large.sim_config)
    with torch.no_grad():
        torch.testing.assert_close(run(read_controller(tmp_path).controller, obs_large)[0], mean_large)
    grids = large.grids
    phases = np.array([0.0] + [m.phase for m in large.sim_config.materials])
    filled = obs_large[:, large.filled_channel].bool()
    channel = {c: i for i, c in enumerate(large.channels)}
    for k, bias, (alpha, psi, ca, cb) in (((0.8, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),
                                          ((0.0, 0.0, 0.0), (0.0, 0.7, 0.0), (0.3, -0.9, 0.2, -0.15))):
        with torch.no_grad():
            net.actor.weight.zero_()
            net.actor.bias.copy_(torch.tensor([alpha, psi, ca, cb]))
            net.wave_k.weight.zero_()
            net.wave_k.bias.copy_(torch.tensor(bias))
            net.wave_k0.copy_(torch.tensor(k))
            mean = run(net, obs_large)[0].double()
        a, b = mean[:, :cells].view(-1, *large.box), mean[:, cells:].view(-1, *large.box)
        heading = torch.from_numpy(large.heading)[:, None, None, None]
        assert headings == "fixed" or heading.abs().min() > 0.1  # (a turn the test can see)
        along, across = k[0] + bias[0], bias[1]  # (the heading's frame)
        place = (along * torch.cos(heading) - across * torch.sin(heading)) * obs_large[:, channel["rel_x"]].double() + \
            (along * torch.sin(heading) + across * torch.cos(heading)) * obs_large[:, channel["rel_y"]].double()
        for n in range(2):
            cell = large.origin[n]
            for i, j, m in filled[n].nonzero().tolist():
                phi = phases[grids[n][cell[0] + i, cell[1] + j, cell[2] + m]]
                for t_over_T in (0.0, 0.3, 0.71):
                    theta = 2 * math.pi * (t_over_T + phi)
                    played = (1.0 if residual else 0.0) * math.sin(theta) + a[n, i, j, m] * math.sin(theta) + \
                        b[n, i, j, m] * math.cos(theta)
                    wave = (1.4 + alpha) * math.sin(2 * math.pi * t_over_T - float(place[n, i, j, m]) - psi)
                    assert abs(float(played) - (wave + ca * math.sin(theta) + cb * math.cos(theta))) < 1e-5
    before = dict(net.init_kwargs, wave={k: v for k, v in net.init_kwargs["wave"].items() if k != "amplitude"})
    assert rebuild(type(net), before).wave["amplitude"] == 1.0  # (a file from before the amplitude: the sine's)
    with pytest.raises(ValueError, match="wave amplitude must be finite and > 0"):
        build_controller(kind, large, hidden=8, head="wave", wave=HandSetWave(amplitude=-1.0))
    with pytest.raises(ValueError, match="head='wave' is for the controllers"):
        build_controller("conv", large, hidden=8, head="wave")
    with pytest.raises(ValueError, match="exactly when control.stroke_periods >= 1"):
        build_controller(kind, two_boxes()[1], hidden=8, head="wave")


@pytest.mark.parametrize("kind", WAVE_KINDS)
def test_a_wave_gain_scales_what_the_head_learnt_beyond_the_hand_set_wave(kind, tmp_path) -> None:
    """Truth: the hand-set wave is the head with its learnt parts zeroed (the evaluation's hand-set row). At gain g a
    trained head commands that wave plus g × (its commands at gain 1 − the wave), along random headings (the wave
    turned by each body's heading): g = 0 is the wave, g = 2.5 extrapolates. The gain travels in controller.pt, a
    file at gain 1 holds no gain key (files as before), and a head without a wave or a negative gain is refused."""
    env = replace_control(two_boxes()[1], stroke_periods=2, residual=True, headings="random")
    obs = env.reset()
    torch.manual_seed(3)
    net = build_controller(kind, env, hidden=8, head="wave", wave=HandSetWave(k=1.5, amplitude=1.6))
    with torch.no_grad():
        for layer in (net.actor, net.wave_k):  # (a head that learnt something: its own wave vector and strokes)
            layer.weight.normal_(std=0.3)
            layer.bias.normal_(std=0.3)
        trained = run(net, obs)[0]
        hand = build_controller(kind, env, hidden=8, head="wave", wave=HandSetWave(k=1.5, amplitude=1.6))
        for layer in (hand.actor, hand.wave_k):
            layer.weight.zero_()
            layer.bias.zero_()
        wave = run(hand, obs)[0]
        assert (trained - wave).abs().max() > 0.1  # (the head moved off the wave: 0 = 0 would pass)
        torch.testing.assert_close(run(with_wave_gain(net, 0.0), obs)[0], wave)
        torch.testing.assert_close(run(with_wave_gain(net, 2.5), obs)[0], wave + 2.5 * (trained - wave))
        torch.testing.assert_close(run(with_wave_gain(net, 1.0), obs)[0], trained)
    assert "gain" not in net.init_kwargs["wave"]
    save_controller(tmp_path / "controller.pt", with_wave_gain(net, 2.5), env.control, env.sim_config)
    saved = read_controller(tmp_path).controller
    assert saved.wave["gain"] == 2.5
    with torch.no_grad():
        torch.testing.assert_close(run(saved, obs)[0], wave + 2.5 * (trained - wave))
    if not isinstance(net, RecurrentPolicy):  # (a teacher's privileged critic around it: the gain reaches the actor)
        privileged = PrivilegedCritic(kind, net.init_kwargs, critic_dim=3, hidden=4)
        privileged.controller.load_state_dict(net.state_dict())
        gained = with_wave_gain(privileged, 2.5)
        assert isinstance(gained, PrivilegedCritic) and gained.controller.wave["gain"] == 2.5
        with torch.no_grad():  # (its critic kept: the head's weights, not a fresh one's)
            privileged.critic_head[-1].weight.fill_(0.7)
        assert torch.equal(with_wave_gain(privileged, 2.5).critic_head[-1].weight, privileged.critic_head[-1].weight)
        with torch.no_grad():
            torch.testing.assert_close(gained.action_params({"policy": obs, "critic": torch.zeros(len(obs), 3)})[0],
                                       wave + 2.5 * (trained - wave))
    with pytest.raises(ValueError, match="wave gain must be finite and >= 0"):
        with_wave_gain(net, -1.0)
    with pytest.raises(ValueError, match="a wave gain needs a wave head"):
        with_wave_gain(build_controller(kind, env, hidden=8, head="stroke"), 2.0)


def replace_control(env: ControlEnv, **changes) -> ControlEnv:
    from dataclasses import replace

    return ControlEnv(env.grids, control=replace(env.control, **changes))


@pytest.mark.parametrize("kind", ["context_gru", "attention_gru"])
def test_the_recurrent_controller_remembers_the_episode_and_forgets_it_at_a_reset(envs_and_obs, kind) -> None:
    """Truth: the same controller stepped one observation at a time (controller_step, the state carried by hand).
    A sequence of T steps in one call gives those outputs; an episode start at step k gives step k's outputs from
    the initial state; the memory is not a no-op (the same last observation after two different histories gives
    different commands); and it is refused behind a privileged critic, naming why."""
    _, env, _, obs = envs_and_obs
    torch.manual_seed(4)
    net = build_controller(kind, env, hidden=8)
    with torch.no_grad():
        net.actor.weight.normal_(std=0.3)  # (commands that show the memory's effect above rounding)
        if kind == "attention_gru":
            net.recall.weight.normal_(std=0.3)  # (its recall starts silent)
        seq = obs[None] + 0.3 * torch.randn(5, *obs.shape) * obs[None, :, env.filled_channel : env.filled_channel + 1]
        start = torch.zeros(5, env.num_envs, dtype=torch.bool)
        start[3, 1] = True  # env 1 starts a new episode at step 3
        mean, _, _, value, state = net(seq, net.initial_state(env.num_envs), start)
        carried = None
        for t in range(5):
            if t == 3:
                carried = (carried[0] * torch.tensor([1.0, 0.0])[:, None, None],)  # env 1's reset, by hand
            (m, _, _, v), carried = controller_step(net, seq[t], carried)
            torch.testing.assert_close(mean[t], m, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(value[t], v, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(state[0], carried[0], rtol=1e-5, atol=1e-6)
        fresh = run(net, seq[3])
        torch.testing.assert_close(mean[3, 1], fresh[0][1], rtol=1e-5, atol=1e-6)  # reset: as from the start
        assert (mean[3, 0] - fresh[0][0]).abs().max() > 1e-4  # env 0 remembers its three steps
    grouped = replace_control(env, privileged_critic=True)
    with pytest.raises(ValueError, match=f"{kind}.*privileged"):
        build_controller(kind, grouped, hidden=8)


def test_the_hypernetwork_starts_as_the_attention_controller_and_its_written_head_keeps_padding_out(envs_and_obs,
                                                                                                    tmp_path) -> None:
    """``attention_hyper`` from a trained ``attention`` controller (``control.controller_init``) gives its commands
    and values exactly (the generator starts at 0). Once the generator is moved, the commands change (the written
    head acts), a body's commands and value are still the same alone in its box as padded beside a larger body
    (the body code that writes the head is a mean over the body's tokens), and the code reads the body channels
    alone."""
    from freeform.run.build import load_controller

    small, large, obs_small, obs_large = envs_and_obs
    torch.manual_seed(7)
    trained = build_controller("attention", large, hidden=8)
    with torch.no_grad():
        for p in trained.parameters():
            p.add_(0.2 * torch.randn_like(p))
    save_controller(tmp_path / "controller.pt", trained, large.control)
    hyper = build_controller("attention_hyper", large, hidden=8)
    load_controller(hyper, str(tmp_path / "controller.pt"))
    with torch.no_grad():
        for a, b in zip(hyper(obs_large), trained(obs_large), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        hyper.generator.weight.normal_(0.0, 0.3)
        hyper.generator.bias.normal_(0.0, 0.3)
        moved, alone = hyper(obs_large), hyper(obs_small)
    assert (moved[0] - trained(obs_large)[0]).abs().max() > 1e-3
    cells = small.box
    on_its_cells = moved[0][0].view(large.box)[: cells[0], : cells[1], : cells[2]].reshape(-1)
    torch.testing.assert_close(on_its_cells, alone[0][0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(moved[3][0], alone[3][0], rtol=1e-5, atol=1e-6)

    # the head is written by what the body is (its voxels, materials, muscles and places), not by its state: the
    # code is unchanged when every other channel (velocity, strain, contact, heading, clock...) changes, and moves
    # with a material
    assert large.channels[: hyper.body_channels] == ("filled", "material", "actuated", "rel_x", "rel_y", "rel_z")
    _, order, valid = hyper.tokens(obs_large)
    code = hyper.body_code(obs_large, order, valid)
    body = obs_large[:, :hyper.body_channels]
    state = obs_large.clone()
    state[:, hyper.body_channels:] += torch.randn_like(state[:, hyper.body_channels:]) * (body[:, :1] > 0)
    torch.testing.assert_close(hyper.body_code(state, order, valid), code, rtol=0, atol=0)
    other = obs_large.clone()
    other[:, 1] *= 0.5  # (the material channel)
    assert (hyper.body_code(other, order, valid) - code).abs().max() > 1e-4


@pytest.mark.parametrize("kind", ["attention", "attention_hyper"])
def test_a_hidden_voxel_is_seen_by_no_other_yet_commands_its_own_cell(kind) -> None:
    """Token dropout's truth (``hiding``, ``algo.token_dropout``): with one voxel of the larger body hidden, any
    change to that voxel's own observation (every channel but ``filled`` and the heading, which every cell of a
    body carries alike) leaves every other cell's command, the body's
    wave vector and the value exactly as they were — it is no key and no part of any pooled summary — while its own
    command still moves (it reads the others); the other body in the batch is untouched by the hiding. Hiding
    nothing is the plain forward to the bit, and hiding every voxel of a body is seeing it whole."""
    large = replace_control(two_boxes()[1], stroke_periods=2)
    obs = large.reset()
    torch.manual_seed(3)
    net = build_controller(kind, large, hidden=8, head="wave")
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.3 * torch.randn_like(p))  # (a trained-looking controller: every term acts)
    cells = math.prod(large.box)
    filled = obs[:, large.filled_channel].flatten(1) > 0.5
    hidden_cell = int(filled[1].nonzero()[2])
    hide = torch.zeros(2, cells, dtype=torch.bool)
    hide[1, hidden_cell] = True
    changed = obs.clone()
    view = changed[1].flatten(1)  # [C, cells]
    body_wide = (large.filled_channel, *net.wave.get("heading_channels", ()))
    own = [c for c in range(view.shape[0]) if c not in body_wide]
    view[own, hidden_cell] += torch.randn(len(own))  # (not filled: it stays a voxel; not the body's heading)
    others = torch.ones(cells, dtype=torch.bool)
    others[hidden_cell] = False
    with torch.no_grad():
        plain = net(obs)
        with net.hiding(hide):
            before, after = net(obs), net(changed)
        with net.hiding(torch.zeros(2, cells, dtype=torch.bool)):
            nothing = net(obs)
        with net.hiding(filled.clone()):
            everything = net(obs)
    strokes = (before[0].view(2, 2, cells), after[0].view(2, 2, cells))
    torch.testing.assert_close(strokes[1][1][:, others], strokes[0][1][:, others], rtol=0, atol=0)
    torch.testing.assert_close(after[3][1], before[3][1], rtol=0, atol=0)  # (the critic's pooled tokens)
    assert (strokes[1][1][:, hidden_cell] - strokes[0][1][:, hidden_cell]).abs().max() > 1e-4
    assert (plain[0][1] - before[0][1]).abs().max() > 1e-4  # (hiding changes what the body's other voxels see)
    torch.testing.assert_close(before[0][0], plain[0][0], rtol=0, atol=0)  # (body 0 hides nothing)
    for a, b in ((nothing, plain), (everything, plain)):
        for x, y in zip(a, b, strict=True):
            torch.testing.assert_close(x, y, rtol=0, atol=0)


def test_the_attention_controller_with_memory_starts_as_the_feed_forward_one_it_grows_from(envs_and_obs,
                                                                                           tmp_path) -> None:
    """control.controller_init of a trained feed-forward ``attention`` controller into ``attention_gru``: every
    weight they share is loaded and the memory's recall is silent, so over an episode of changing observations the
    recurrent controller gives the feed-forward one's commands and values at every step (to rounding). A file of
    another kind is still refused, naming it."""
    from freeform.run.build import load_controller

    _, env, _, obs = envs_and_obs
    torch.manual_seed(5)
    trained = build_controller("attention", env, hidden=8, head="direct")
    with torch.no_grad():
        for p in trained.parameters():
            p.add_(0.2 * torch.randn_like(p))  # (a trained controller, not the fresh init)
    save_controller(tmp_path / "controller.pt", trained, env.control)
    grown = build_controller("attention_gru", env, hidden=8)
    load_controller(grown, str(tmp_path / "controller.pt"))
    seq = obs[None] + 0.3 * torch.randn(4, *obs.shape) * obs[None, :, env.filled_channel: env.filled_channel + 1]
    with torch.no_grad():
        *out, _ = grown(seq, grown.initial_state(env.num_envs), torch.zeros(4, env.num_envs, dtype=torch.bool))
        for t in range(4):
            for a, b in zip(out, trained(seq[t]), strict=True):
                torch.testing.assert_close(a[t], b, rtol=1e-6, atol=1e-7)  # (batched over T·N: rounding)
    save_controller(tmp_path / "context" / "controller.pt", build_controller("context", env, hidden=8), env.control)
    with pytest.raises(ValueError, match="holds another controller than this run builds"):
        load_controller(grown, str(tmp_path / "context" / "controller.pt"))
