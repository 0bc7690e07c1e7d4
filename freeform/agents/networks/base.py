"""Actor-critic networks: the contracts PPO relies on, declared (:class:`ActorCritic`, :class:`SplitActorCritic`,
:class:`DeclaresDistribution`, :class:`Rebuildable`, :class:`GroupedActions`), and the paper's voxel network, a
small MLP for flat observations (and its observation-group form). The networks are leaves: the control env's
controllers (``freeform.agents.networks.controllers``) and the co-design actor-critic (``freeform.agents.networks.codesign_network``)
build on them, never the other way.

A policy is an ``nn.Module`` whose ``forward(obs)`` returns its action distribution's parameters, then the critic's
V(obs) ``[N]``: for Box actions ``(mean [N, A], log_std [N, A], value [N])``, the Gaussian policy
π = Normal(mean, exp(log_std)) over raw actions; for discrete ones ``(logits, value)``
(``freeform.distributions`` lists them). A policy that keeps its
constructor arguments in ``init_kwargs`` can be rebuilt by a checkpoint from the file alone, and one that names
groups of action dimensions in ``action_groups`` gets the mean σ of each group logged.

A policy whose actor and critic share no layers may also define ``action_params(obs) -> (mean, log_std)`` and
``value(obs) -> [N]`` (the two halves of ``forward``): PPO then runs only the actor at each rollout step and the
critic once over the whole rollout, which with one env is most of the acting cost left.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import torch
import torch.nn as nn
import torch.nn.functional as F

from freeform.agents.networks.fast_trunk import onehot_conv3d_voxel_major, strided_conv3d_voxel_major
from freeform.agents.networks.gather_trunk import onehot_conv3d_gather, strided_conv3d_gather
from freeform.agents.networks.observation_groups import CRITIC, GROUPS, POLICY, is_grouped
from freeform.distributions import (
    ActionDistribution,
    DiagGaussian,
    MaskedDiagGaussian,
    from_spec,
    head_distribution,
)

TRUNK_IMPLEMENTATIONS = ("auto", "fast", "gather", "conv")


def resolve_trunk(trunk: str, device: torch.device | str, graphed: bool = False) -> str:
    """The form ``VoxelActorCritic``'s "auto" trunk takes (the same function every way; measured on one H200,
    ``docs/physics.md``, "The GPU"): the sparse "fast" form on the CPU; on a GPU the deterministic "gather" form when
    PyTorch is asked for deterministic algorithms (``torch.use_deterministic_algorithms`` or
    ``torch.backends.cudnn.deterministic``: cuSPARSE's and cuDNN's products may sum in a varying order), else the
    "fast" form's CSR products inside a CUDA graph (``graphed``: 0.77 ms a minibatch step against cuDNN's 2.37 and
    the gather form's 1.65) and cuDNN's "conv" eagerly (4.6 ms against the CSR products' 6.0). Any other name is
    returned as given."""
    if trunk != "auto":
        return trunk
    if torch.device(device).type == "cpu":
        return "fast"
    if torch.are_deterministic_algorithms_enabled() or torch.backends.cudnn.deterministic:
        return "gather"
    return "fast" if graphed else "conv"


@runtime_checkable
class ActorCritic(Protocol):
    """``policy(obs [N, ...]) -> (*params, value [N])``: the action distribution's parameters (a Gaussian's
    ``mean [N, A], log_std [N, A]``; a categorical's ``logits [N, n]``), then V (PPO checks the shapes on its env)."""

    def __call__(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]: ...


@runtime_checkable
class SplitActorCritic(ActorCritic, Protocol):
    """An actor-critic whose halves run apart: ``action_params(obs) -> params`` (a tuple) and ``value(obs) -> [N]``,
    equal to ``forward``'s (PPO checks it)."""

    def action_params(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]: ...

    def value(self, obs: torch.Tensor) -> torch.Tensor: ...


@runtime_checkable
class DeclaresDistribution(Protocol):
    """A network that says which action distribution its outputs parameterise (``distribution``, an
    ``ActionDistribution``); PPO uses it, and refuses an env whose actions need another. Without it PPO takes the
    env's (``action_distribution``) or a Gaussian."""

    distribution: ActionDistribution


@runtime_checkable
class Rebuildable(Protocol):
    """A network a checkpoint can rebuild from the file alone: ``init_kwargs``, its constructor's arguments."""

    init_kwargs: dict[str, Any]


@runtime_checkable
class GroupedActions(Protocol):
    """A network whose groups of action dimensions PPO logs the mean σ of: ``action_groups``, name -> a slice."""

    action_groups: dict[str, slice]


def rebuild(cls: type[nn.Module], init_kwargs: dict[str, Any]) -> nn.Module:
    """The network ``cls`` rebuilt from its ``init_kwargs`` (what a checkpoint holds): ``cls(**init_kwargs)``, or
    ``cls.from_init_kwargs(init_kwargs)`` for a network whose constructor takes some of them grouped (the
    controllers' ``ControlInputs``, the co-design network's ``CodesignObservation``)."""
    from_kwargs = getattr(cls, "from_init_kwargs", None)
    return from_kwargs(dict(init_kwargs)) if from_kwargs is not None else cls(**init_kwargs)


def _xavier_zero(layer: nn.Linear) -> nn.Linear:
    """Xavier-uniform weights, zero bias: the spec's head init, which makes the untrained policy ≈ N(0, I)."""
    nn.init.xavier_uniform_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class VoxelActorCritic(nn.Module):
    """The paper's actor-critic over a voxel grid of material indices (spec ``ppo.md``, "Network").

    Shared trunk: one-hot [N, k, ρ, ρ, ρ] → Conv3d(k→1, 3³, pad 1) → ReLU → Conv3d(1→1, 5³, stride 2, pad 2) → ReLU
    → flatten (⌈ρ/2⌉³) → Linear(→ h), no activation. Actor: Linear(h→h) → ReLU → Linear(h → 2(3+k)) = (μ, log σ),
    state-dependent and unclamped. Critic: Linear(h→h) → ReLU → Linear(h→1).

    ``trunk="fast"`` computes the two convolutions as sparse-matrix products without building the one-hot tensor
    (``freeform.agents.networks.fast_trunk``; its speed against ``nn.Conv3d``: ``python -m benchmarks ppo``, docs/ppo.md);
    ``trunk="gather"`` computes them as fixed-shape gathers and dense products, deterministic and free of host
    synchronisation (``freeform.agents.networks.gather_trunk``); ``trunk="conv"`` runs the plain ``nn.Conv3d`` layers;
    ``"auto"`` (default) picks by device (``resolve_trunk``; the trainer resolves it knowing whether the update is a
    CUDA graph). All read the same parameters (``conv1``, ``conv2``), so state dicts are
    interchangeable, and a test pins the two computations equal (outputs and gradients).

    ``distribution``: the paper's Gaussian over the design action ``[x, y, z, w_0 … w_{k−1}]`` (None, the default),
    or another one (an ``ActionDistribution`` or its ``spec()``; not a masked one): the same trunk then ends in that
    distribution's logits, Linear(h → Σ logits), Xavier like the Gaussian's head — e.g. a categorical over grid cells
    for a design env of your own with discrete actions.
    """

    def __init__(self, resolution: int = 20, materials: int = 2, hidden: int = 128, trunk: str = "auto",
                 distribution: ActionDistribution | dict[str, Any] | None = None) -> None:
        """``resolution`` ρ: grid edge; ``materials`` k: material count incl. empty (index 0); ``hidden`` h."""
        super().__init__()
        if not isinstance(resolution, int) or resolution < 2:
            raise ValueError(f"resolution must be an int >= 2, got {resolution!r}")
        if not isinstance(materials, int) or not 2 <= materials <= 255:
            raise ValueError(f"materials must be an int in [2, 255] (uint8 grids), got {materials!r}")
        if not isinstance(hidden, int) or hidden < 1:
            raise ValueError(f"hidden must be a positive int, got {hidden!r}")
        if trunk not in TRUNK_IMPLEMENTATIONS:
            raise ValueError(f"trunk must be one of {TRUNK_IMPLEMENTATIONS}, got {trunk!r}")
        self.init_kwargs: dict[str, Any] = dict(resolution=resolution, materials=materials, hidden=hidden, trunk=trunk)
        self.resolution = resolution
        self.materials = materials
        self.hidden = hidden
        self.trunk = trunk
        dist = DiagGaussian(3 + materials) if distribution is None else from_spec(distribution)
        if isinstance(dist, MaskedDiagGaussian):
            raise ValueError("VoxelActorCritic has no head for a MaskedDiagGaussian: use ConvController")
        self.gaussian = type(dist) is DiagGaussian
        if distribution is not None:
            self.init_kwargs["distribution"] = dist.spec()
        self.action_dim = dist.action_dim
        self.distribution = dist
        # The action layout is [x, y, z, w_0 … w_{k-1}] (spec design.md, "Action → bundle").
        self.action_groups = ({"position": slice(0, 3), "material": slice(3, 3 + materials)}
                              if self.gaussian and self.action_dim == 3 + materials else {})

        self.conv1 = nn.Conv3d(materials, 1, kernel_size=3, stride=1, padding=1)
        self.conv2 = nn.Conv3d(1, 1, kernel_size=5, stride=2, padding=2)
        half = math.ceil(resolution / 2)  # Conv3d output edge: floor((ρ + 2·2 − 5) / 2) + 1
        self.trunk_fc = nn.Linear(half**3, hidden)
        self.actor_fc = _xavier_zero(nn.Linear(hidden, hidden))
        self.actor_out = _xavier_zero(nn.Linear(hidden, 2 * self.action_dim if self.gaussian else dist.param_dims[0]))
        self.critic_fc = _xavier_zero(nn.Linear(hidden, hidden))
        self.critic_out = _xavier_zero(nn.Linear(hidden, 1))

    def one_hot(self, grids: torch.Tensor) -> torch.Tensor:
        """uint8 ``[N, ρ, ρ, ρ]`` → float ``[N, k, ρ, ρ, ρ]`` (channel c = 1 where the voxel holds material c)."""
        channels = torch.arange(self.materials, device=grids.device, dtype=grids.dtype).view(1, -1, 1, 1, 1)
        return (grids.unsqueeze(1) == channels).to(self.conv1.weight.dtype)

    def features(self, grids: torch.Tensor) -> torch.Tensor:
        """uint8 ``[N, ρ, ρ, ρ]`` → trunk features float ``[N, h]``."""
        rho = self.resolution
        if grids.dim() != 4 or tuple(grids.shape[1:]) != (rho, rho, rho):
            raise ValueError(f"grids must have shape [N, {rho}, {rho}, {rho}], got {tuple(grids.shape)}")
        trunk = resolve_trunk(self.trunk, grids.device)
        if trunk == "fast":
            # Voxel-major activations [voxels, N] throughout; the transpose at the end is free for the matmul.
            # In-place ReLUs: the sparse layers' backward passes do not read their outputs; saves two 4 MB passes.
            # Off the CPU always the CSR product: the scatter reads a count on the host and sums with atomics.
            x = F.relu(onehot_conv3d_voxel_major(grids, self.conv1.weight, self.conv1.bias,
                                                 dense=grids.device.type != "cpu"), inplace=True)
            x = F.relu(strided_conv3d_voxel_major(x, rho, self.conv2.weight, self.conv2.bias), inplace=True)
            return self.trunk_fc(x.t())
        if trunk == "gather":
            x = F.relu(onehot_conv3d_gather(grids, self.conv1.weight, self.conv1.bias), inplace=True)
            x = F.relu(strided_conv3d_gather(x, rho, self.conv2.weight, self.conv2.bias))  # (a view: not in place)
            return self.trunk_fc(x)
        x = F.relu(self.conv1(self.one_hot(grids)))
        x = F.relu(self.conv2(x))
        return self.trunk_fc(x.flatten(1))

    def for_export(self) -> VoxelActorCritic:
        """The same network on the plain ``Conv3d`` trunk (the same function; ``torch.export`` traces it, not the
        sparse CPU trunk): what ``PPO.export`` writes."""
        twin = copy.deepcopy(self)
        twin.trunk = "conv"
        return twin

    def forward(self, grids: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """uint8 ``[N, ρ, ρ, ρ]`` → (mean ``[N, 3+k]``, log_std ``[N, 3+k]``, value ``[N]``), or (logits, value)."""
        z = self.features(grids)
        head = self.actor_out(F.relu(self.actor_fc(z)))
        value = self.critic_out(F.relu(self.critic_fc(z))).squeeze(-1)
        if self.gaussian:
            mean, log_std = head.chunk(2, dim=-1)
            return mean, log_std, value
        return head, value


class MLPActorCritic(nn.Module):
    """Separate tanh MLPs for actor and critic over flat observations, with the head the action distribution needs.

    CleanRL's networks (``ppo_continuous_action.py`` for Box actions, ``ppo.py`` for discrete ones): orthogonal init
    (√2 hidden, 0.01 policy output, 1 value output), so the untrained policy is ≈ N(0, I) or ≈ uniform. The actor
    outputs a Gaussian's mean with a state-independent log σ (``distribution`` a ``DiagGaussian``, the default over
    ``action_dim`` floats), or the logits of a ``Categorical``, ``MultiCategorical`` or ``Bernoulli``.
    Observations may be any dtype (uint8 images stay uint8 until here) and shape (flattened).
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int | None = None,
        hidden: tuple[int, ...] | list[int] = (64, 64),
        distribution: ActionDistribution | dict[str, Any] | None = None,
    ) -> None:
        """``distribution``: an ``ActionDistribution`` or its ``spec()`` (None: a Gaussian over ``action_dim``);
        ``action_dim`` may then be left out (it must agree when given)."""
        super().__init__()
        if not isinstance(obs_dim, int) or obs_dim < 1:
            raise ValueError(f"obs_dim must be a positive int, got {obs_dim!r}")
        dist = head_distribution(distribution, action_dim, "MLPActorCritic", " (its mask comes from the observation): "
                                 "use MLPController or ConvController for a control env")
        hidden = tuple(hidden)
        if not hidden or not all(isinstance(h, int) and h > 0 for h in hidden):
            raise ValueError(f"hidden must be a non-empty sequence of positive ints, got {hidden!r}")
        self.init_kwargs: dict[str, Any] = dict(obs_dim=obs_dim, action_dim=dist.action_dim, hidden=hidden)
        if not isinstance(dist, DiagGaussian):  # (a Gaussian's checkpoint reads as it always did)
            self.init_kwargs["distribution"] = dist.spec()
        self.obs_dim = obs_dim
        self.action_dim = dist.action_dim
        self.distribution = dist
        self.action_groups: dict[str, slice] = {}
        self.gaussian = isinstance(dist, DiagGaussian)

        def mlp(out_dim: int, out_gain: float) -> nn.Sequential:
            layers: list[nn.Module] = []
            width = obs_dim
            for h in hidden:
                layers += [self._orthogonal(nn.Linear(width, h), math.sqrt(2.0)), nn.Tanh()]
                width = h
            layers.append(self._orthogonal(nn.Linear(width, out_dim), out_gain))
            return nn.Sequential(*layers)

        self.actor = mlp(dist.param_dims[0], 0.01)  # the mean, or the logits
        self.critic = mlp(1, 1.0)
        if self.gaussian:
            self.log_std = nn.Parameter(torch.zeros(dist.action_dim))
        # The Linear layers in order (plain tuples: not registered twice), for a forward without module calls.
        self._actor_linears = tuple(self.actor[::2])
        self._critic_linears = tuple(self.critic[::2])

    @classmethod
    def for_env(cls, env: Any, hidden: tuple[int, ...] | list[int] = (64, 64)) -> MLPActorCritic:
        """The network for a ``VecEnv``: its flattened observation size and its ``action_distribution`` (a
        Gaussian over ``action_dim`` where it declares none). An env observing the groups ``"policy"`` and
        ``"critic"`` gets the grouped network (``freeform.agents.networks.observation_groups``)."""
        if is_grouped(env.observation_shape):
            return GroupedMLPActorCritic.for_env(env, hidden)
        if isinstance(env.observation_shape, Mapping):
            raise ValueError(f"MLPActorCritic reads one flat observation, and this env observes a dict of them "
                             f"{dict(env.observation_shape)}: flatten them (from_gymnasium's default) or write a "
                             "network that reads the parts by name")
        return cls(int(math.prod(env.observation_shape)), int(env.action_dim), hidden,
                   getattr(env, "action_distribution", None))

    @staticmethod
    def _orthogonal(layer: nn.Linear, gain: float) -> nn.Linear:
        nn.init.orthogonal_(layer.weight, gain)
        nn.init.zeros_(layer.bias)
        return layer

    @staticmethod
    def _mlp(linears: tuple[nn.Linear, ...], x: torch.Tensor) -> torch.Tensor:
        """The Sequential's computation (Linear, tanh, …, Linear) without its per-module call overhead."""
        for layer in linears[:-1]:
            x = torch.tanh(F.linear(x, layer.weight, layer.bias))
        return F.linear(x, linears[-1].weight, linears[-1].bias)

    def _flat(self, obs: torch.Tensor) -> torch.Tensor:
        # Reshaped and cast only where needed: with one env (acting every step) a no-op op still costs its dispatch.
        if obs.dim() != 2:
            obs = obs.reshape(obs.shape[0], -1)
        dtype = self._critic_linears[0].weight.dtype
        return obs if obs.dtype == dtype else obs.to(dtype)

    def action_params(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, obs_dim]`` → the distribution's parameters: (mean ``[N, A]``, log_std ``[N, A]``) or (logits,)."""
        out = self._mlp(self._actor_linears, self._flat(obs))
        return (out, self.log_std.expand_as(out)) if self.gaussian else (out,)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """``[N, obs_dim]`` → V(obs) ``[N]``."""
        return self._mlp(self._critic_linears, self._flat(obs)).squeeze(-1)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, obs_dim]`` → (*the distribution's parameters, value ``[N]``)."""
        return (*self.action_params(obs), self.value(obs))


class GroupedMLPActorCritic(MLPActorCritic):
    """:class:`~freeform.agents.MLPActorCritic` over observation groups: the actor's MLP reads ``obs["policy"]``
    only, the critic's the two groups side by side (``[policy, critic]``, each flattened). Otherwise CleanRL's nets
    as there (orthogonal init, state-independent log σ, any of the discrete heads)."""

    def __init__(self, policy_dim: int, critic_dim: int, action_dim: int | None = None,
                 hidden: tuple[int, ...] | list[int] = (64, 64),
                 distribution: ActionDistribution | dict[str, Any] | None = None) -> None:
        super().__init__(policy_dim, action_dim, hidden, distribution)
        if not isinstance(critic_dim, int) or critic_dim < 1:
            raise ValueError(f"critic_dim must be a positive int, got {critic_dim!r}")
        first = self.critic[0]  # the critic's first layer reads both groups
        self.critic[0] = self._orthogonal(nn.Linear(policy_dim + critic_dim, first.out_features), math.sqrt(2.0))
        self._critic_linears = tuple(self.critic[::2])
        self.init_kwargs = {"policy_dim": policy_dim, "critic_dim": critic_dim,
                            **{k: v for k, v in self.init_kwargs.items() if k != "obs_dim"}}
        self.critic_dim = critic_dim

    @classmethod
    def for_env(cls, env: Any, hidden: tuple[int, ...] | list[int] = (64, 64)) -> GroupedMLPActorCritic:  # type: ignore[override]
        """The network for a ``VecEnv`` observing the two groups (each part's size flattened)."""
        shape = env.observation_shape
        if not is_grouped(shape):
            raise ValueError(f"GroupedMLPActorCritic needs observations with the groups {GROUPS}, got {shape}")
        return cls(int(math.prod(shape[POLICY])), int(math.prod(shape[CRITIC])), int(env.action_dim), hidden,
                   getattr(env, "action_distribution", None))

    def action_params(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:  # type: ignore[override]
        """``obs["policy"] [N, P]`` → the distribution's parameters; the critic group is never read."""
        return super().action_params(obs[POLICY])

    def value(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:  # type: ignore[override]
        """``obs["policy"] [N, P]``, ``obs["critic"] [N, C]`` → V ``[N]``."""
        return super().value(torch.cat([self._flat(obs[POLICY]), self._flat(obs[CRITIC])], dim=1))


__all__ = ["ActorCritic", "DeclaresDistribution", "GroupedActions", "GroupedMLPActorCritic", "MLPActorCritic",
           "Rebuildable", "SplitActorCritic", "TRUNK_IMPLEMENTATIONS", "VoxelActorCritic", "rebuild", "resolve_trunk"]
