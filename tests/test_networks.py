"""Networks: the paper's parameter counts, the init (untrained policy ≈ N(0, I)), the fast trunk = nn.Conv3d trunk."""

from __future__ import annotations

from typing import Any

import pytest
import torch
import torch.nn.functional as F

from freeform.agents import MLPActorCritic, VoxelActorCritic
from freeform.agents.networks.fast_trunk import onehot_conv3d, strided_conv3d

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def n_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


@pytest.mark.parametrize("materials,hidden,expected", [(2, 128, 162_752), (4, 256, 391_930)])
def test_parameter_counts_match_the_spec(materials: int, hidden: int, expected: int) -> None:
    assert n_params(VoxelActorCritic(resolution=20, materials=materials, hidden=hidden)) == expected


def test_layer_shapes_are_the_papers() -> None:
    net = VoxelActorCritic(resolution=20, materials=4, hidden=256)
    assert net.conv1.weight.shape == (1, 4, 3, 3, 3) and net.conv1.padding == (1, 1, 1)
    assert net.conv2.weight.shape == (1, 1, 5, 5, 5) and net.conv2.stride == (2, 2, 2) and net.conv2.padding == (2, 2, 2)
    assert net.trunk_fc.weight.shape == (256, 1000)
    assert net.actor_out.weight.shape == (14, 256) and net.critic_out.weight.shape == (1, 256)
    mean, log_std, value = net(torch.zeros(3, 20, 20, 20, dtype=torch.uint8))
    assert mean.shape == log_std.shape == (3, 7) and value.shape == (3,)


def test_head_init_is_xavier_with_zero_bias() -> None:
    net = VoxelActorCritic(resolution=20, materials=2, hidden=128)
    for layer in (net.actor_fc, net.actor_out, net.critic_fc, net.critic_out):
        assert torch.all(layer.bias == 0)
        bound = (6.0 / (layer.in_features + layer.out_features)) ** 0.5
        assert layer.weight.abs().max() <= bound and layer.weight.abs().max() > 0.9 * bound


@pytest.mark.parametrize("materials,hidden", [(2, 128), (4, 256)])
def test_untrained_policy_is_near_standard_normal_on_an_empty_grid(materials: int, hidden: int) -> None:
    """Over 20 random inits: μ ≈ 0 and log σ ≈ 0 on the empty grid (the spec's "≈ N(0, I)")."""
    empty = torch.zeros(1, 20, 20, 20, dtype=torch.uint8)
    means, log_stds = [], []
    for seed in range(20):
        torch.manual_seed(seed)
        mean, log_std, _ = VoxelActorCritic(20, materials, hidden)(empty)
        means.append(mean)
        log_stds.append(log_std)
    means, log_stds = torch.cat(means), torch.cat(log_stds)
    assert means.abs().max() < 0.5 and log_stds.abs().max() < 0.5
    assert means.mean().abs() < 0.1 and log_stds.mean().abs() < 0.1
    assert means.square().mean().sqrt() < 0.25  # per-dimension spread across inits stays well under σ = 1


def test_mlp_policy_shapes_and_init() -> None:
    net = MLPActorCritic(obs_dim=6, action_dim=3, hidden=(32, 32))
    mean, log_std, value = net(torch.randn(5, 6))
    assert mean.shape == log_std.shape == (5, 3) and value.shape == (5,)
    assert torch.all(log_std == 0) and mean.abs().max() < 0.2
    assert net.init_kwargs == {"obs_dim": 6, "action_dim": 3, "hidden": (32, 32)}


@pytest.mark.parametrize(
    "kwargs,name",
    [({"resolution": 1}, "resolution"), ({"materials": 1}, "materials"), ({"materials": 300}, "materials"),
     ({"hidden": 0}, "hidden"), ({"trunk": "winograd"}, "trunk")],
)
def test_voxel_network_rejects_bad_arguments(kwargs: dict[str, Any], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        VoxelActorCritic(**kwargs)


def test_voxel_network_rejects_a_wrong_grid_shape() -> None:
    with pytest.raises(ValueError, match="grids"):
        VoxelActorCritic(resolution=8)(torch.zeros(2, 8, 8, 4, dtype=torch.uint8))


@pytest.mark.parametrize("bad", [{"obs_dim": 0}, {"action_dim": -1}, {"hidden": ()}])
def test_mlp_rejects_bad_arguments(bad: dict[str, Any]) -> None:
    kwargs = {"obs_dim": 3, "action_dim": 2} | bad
    with pytest.raises(ValueError, match=next(iter(bad))):
        MLPActorCritic(**kwargs)


# ---------------------------------------------------------------------------------------------------------------
# The fast trunk must be the paper's network: equal outputs and gradients to plain nn.Conv3d.
# ---------------------------------------------------------------------------------------------------------------


def random_grids(n: int, rho: int, k: int, seed: int, fill: float = 0.6) -> torch.Tensor:
    """Grids with a fraction ``fill`` of voxels holding a random material ≥ 1 (design states are ≤ ~5 % full; the
    fast layer scatters sparse grids and multiplies dense ones, so tests cover both)."""
    g = torch.Generator().manual_seed(seed)
    materials = torch.randint(1, k, (n, rho, rho, rho), generator=g, dtype=torch.uint8)
    grids = torch.where(torch.rand(n, rho, rho, rho, generator=g) < fill, materials, 0).to(torch.uint8)
    grids[0] = 0  # an empty grid, the state every episode starts from
    if fill >= 0.5:
        grids[1] = k - 1  # a full one: every border case of the padding at once
    else:
        ends = torch.tensor([0, rho - 1])
        grids[1, ends[:, None, None], ends[None, :, None], ends[None, None, :]] = k - 1  # the 8 corners
        grids[1, 0, :, 0] = 1  # and one border edge: sparse, yet every padding case
    return grids


def _randomise(net: VoxelActorCritic, seed: int) -> None:
    """Weights far from the init (incl. negative biases that make ReLUs cut) so every branch is exercised."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)


@pytest.mark.parametrize("fill", [0.6, 0.005])
@pytest.mark.parametrize("rho,k", [(20, 2), (20, 4), (7, 3), (6, 5)])
def test_onehot_conv_equals_conv3d_of_the_one_hot(rho: int, k: int, fill: float) -> None:
    grids = random_grids(6 if fill > 0.5 else 40, rho, k, seed=rho * k, fill=fill)
    weight = torch.randn(1, k, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(1, dtype=torch.float64, requires_grad=True)
    one_hot = F.one_hot(grids.long(), k).permute(0, 4, 1, 2, 3).double()
    expected = F.conv3d(one_hot, weight, bias, padding=1)
    got = onehot_conv3d(grids, weight, bias)
    torch.testing.assert_close(got, expected)
    upstream = torch.randn_like(expected)
    gw_expected, gb_expected = torch.autograd.grad(expected, (weight, bias), upstream)
    gw, gb = torch.autograd.grad(got, (weight, bias), upstream)
    torch.testing.assert_close(gw, gw_expected)
    torch.testing.assert_close(gb, gb_expected)


def test_both_first_layer_paths_are_taken() -> None:
    """The density switch: design-like grids scatter, dense ones multiply (guards the tests above)."""
    from freeform.agents.networks import fast_trunk

    calls: list[str] = []
    scatter, spmm = fast_trunk.OccupiedScatterConv.apply, fast_trunk.SparseConv.apply
    w, b = torch.randn(1, 2, 3, 3, 3), torch.randn(1)
    try:
        fast_trunk.OccupiedScatterConv.apply = lambda *a: calls.append("scatter") or scatter(*a)
        fast_trunk.SparseConv.apply = lambda *a: calls.append("spmm") or spmm(*a)
        onehot_conv3d(random_grids(40, 8, 2, seed=0, fill=0.005), w, b)
        onehot_conv3d(random_grids(40, 8, 2, seed=0, fill=0.6), w, b)
        sparse = random_grids(40, 8, 2, seed=0, fill=0.005)  # dense=True (the GPU's): the product, however sparse
        expected = fast_trunk.onehot_conv3d_voxel_major(sparse, w, b)
        torch.testing.assert_close(fast_trunk.onehot_conv3d_voxel_major(sparse, w, b, dense=True), expected)
    finally:
        fast_trunk.OccupiedScatterConv.apply, fast_trunk.SparseConv.apply = scatter, spmm
    assert calls == ["scatter", "spmm", "scatter", "spmm"]


def test_auto_trunk_rule() -> None:
    """"auto": the sparse form on the CPU; on a GPU the CSR products inside a CUDA graph, cuDNN eagerly, the gather
    form whenever deterministic algorithms are asked for (cuSPARSE's and cuDNN's sums vary in order)."""
    from freeform.agents.networks import resolve_trunk

    assert [resolve_trunk("auto", "cpu"), resolve_trunk("auto", "cpu", graphed=True)] == ["fast", "fast"]
    assert [resolve_trunk("auto", "cuda"), resolve_trunk("auto", "cuda", graphed=True)] == ["conv", "fast"]
    with torch.backends.cudnn.flags(enabled=True, deterministic=True):
        assert resolve_trunk("auto", "cuda", graphed=True) == resolve_trunk("auto", "cuda") == "gather"
    assert [resolve_trunk(t, "cuda", graphed=True) for t in ("conv", "gather", "fast")] == ["conv", "gather", "fast"]


@pytest.mark.parametrize("rho", [20, 7, 6])
def test_strided_conv_equals_conv3d(rho: int) -> None:
    g = torch.Generator().manual_seed(rho)
    x = torch.randn(5, 1, rho, rho, rho, generator=g, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(1, 1, 5, 5, 5, generator=g, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(1, generator=g, dtype=torch.float64, requires_grad=True)
    expected = F.conv3d(x, weight, bias, stride=2, padding=2)
    got = strided_conv3d(x, weight, bias)
    torch.testing.assert_close(got, expected)
    upstream = torch.randn(expected.shape, generator=g, dtype=torch.float64)
    for a, b in zip(torch.autograd.grad(got, (x, weight, bias), upstream), torch.autograd.grad(expected, (x, weight, bias), upstream), strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("fill", [0.6, 0.005])
@pytest.mark.parametrize("rho,k", [(20, 4), (7, 3), (6, 2)])
def test_gather_trunk_layers_equal_conv3d(rho: int, k: int, fill: float) -> None:
    """The GPU's gather form (``gather_trunk``): both layers = F.conv3d, outputs and every gradient, float64."""
    from freeform.agents.networks.gather_trunk import onehot_conv3d_gather, strided_conv3d_gather

    g = torch.Generator().manual_seed(rho + k)
    grids = random_grids(5, rho, k, seed=rho * k + 1, fill=fill)
    w1 = torch.randn(1, k, 3, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b1 = torch.randn(1, generator=g, dtype=torch.float64, requires_grad=True)
    w2 = torch.randn(1, 1, 5, 5, 5, generator=g, dtype=torch.float64, requires_grad=True)
    b2 = torch.randn(1, generator=g, dtype=torch.float64, requires_grad=True)
    one_hot = F.one_hot(grids.long(), k).permute(0, 4, 1, 2, 3).double()
    h_expected = F.conv3d(one_hot, w1, b1, padding=1)
    h = onehot_conv3d_gather(grids, w1, b1)
    torch.testing.assert_close(h, h_expected.reshape(5, rho**3))
    # the second layer on the first's output (its input gradient reaches the first layer's weights)
    y_expected = F.conv3d(h_expected.relu(), w2, b2, stride=2, padding=2)
    y = strided_conv3d_gather(h.relu(), rho, w2, b2)
    torch.testing.assert_close(y, y_expected.reshape(5, -1))
    upstream = torch.randn(y.shape, generator=g, dtype=torch.float64)
    params = (w1, b1, w2, b2)
    for a, b in zip(torch.autograd.grad(y, params, upstream), torch.autograd.grad(y_expected, params, upstream.view_as(y_expected)), strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("fill", [0.6, 0.005])
@pytest.mark.parametrize("k,hidden,trunk", [(2, 128, "fast"), (4, 256, "fast"), (4, 256, "gather")])
def test_fast_network_equals_plain_network(k: int, hidden: int, fill: float, trunk: str) -> None:
    """Whole network, float32, the paper's sizes: same outputs and same parameter gradients."""
    fast = VoxelActorCritic(20, k, hidden, trunk=trunk)
    _randomise(fast, seed=k)
    plain = VoxelActorCritic(20, k, hidden, trunk="conv")
    plain.load_state_dict(fast.state_dict())
    grids = random_grids(16 if fill > 0.5 else 64, 20, k, seed=k, fill=fill)
    outs_fast, outs_plain = fast(grids), plain(grids)
    for a, b in zip(outs_fast, outs_plain, strict=True):  # float32 sums in another order: relative to the scale
        scale = b.abs().max().clamp_min(1.0)
        torch.testing.assert_close(a / scale, b / scale, rtol=1e-4, atol=1e-5)
    loss = lambda outs: outs[0].square().sum() + outs[1].sum() + (outs[2] - 1).square().sum()
    loss(outs_fast).backward()
    loss(outs_plain).backward()
    for (name, pf), pp in zip(fast.named_parameters(), plain.parameters(), strict=True):
        scale = pp.grad.abs().max().clamp_min(1.0)
        torch.testing.assert_close(pf.grad / scale, pp.grad / scale, rtol=1e-4, atol=1e-4, msg=name)
