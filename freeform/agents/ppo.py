"""Batched PPO, written out top to bottom: rollout → returns/advantages → loss → update → KL schedule.

The default configuration reproduces the semantics of RLlib 2.0.1's PPO as the paper used it (spec ``ppo.md``):
GAE with λ = 1 (advantage = discounted return − V), advantages standardised once over the whole train batch, the
clipped surrogate, the squared value error clamped at ``vf_clip_param``, a KL(π_old ‖ π) penalty whose coefficient
adapts after every epoch, Adam without gradient clipping. Common variants are switches in ``PPOConfig``.

Shapes: ``T`` = ``rollout_steps``, ``N`` = ``env.num_envs``, ``A`` = ``env.action_dim``, ``B`` = ``T·N``.

Every collective sits behind ``self.dp`` (``freeform.agents.distributed.Collectives``), the identity in one process:
the code below is the single-process algorithm. Under ``torch.distributed`` (a process group of R > 1 ranks, e.g.
``torchrun``) each rank's env holds its slice of the environments, ``self.dp`` is a ``DataParallel`` and the update
uses the statistics of the global batch; the rules are in ``distributed.py`` (``docs/scaling.md``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
import types
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch
import torch.nn as nn

from freeform.agents import distributed
from freeform.agents.distributed import PER_ENV
from freeform.agents.flat_params import FlatParameters
from freeform.agents.normalization import RunningMeanStd
from freeform.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from freeform.envs.base import VecEnv
from freeform.learner import Episodes
from freeform.records import EpisodeCollector
from freeform.validation import is_int, is_number, require

ADVANTAGE_NORMS = ("batch", "minibatch", "none")
VALUE_CLIP_MODES = ("squared", "ppo2")
LR_SCHEDULES = ("constant", "linear")


@dataclass
class PPOConfig:
    """PPO hyper-parameters. The defaults are RLlib 2.0.1's PPO with the paper's overrides (Table I)."""

    lr: float = 1e-4
    """Adam learning rate (paper: 1e-4)."""
    gamma: float = 0.99
    """Discount factor γ."""
    gae_lambda: float = 1.0
    """GAE λ; 1 = plain discounted return minus V (the paper: "GAE disabled")."""
    clip_param: float = 0.3
    """Surrogate clip ε: the ratio π/π_old is clipped to [1 − ε, 1 + ε]."""
    kl_coeff: float = 0.2
    """Initial coefficient β of the KL(π_old ‖ π) penalty; 0 disables the penalty (β then stays 0)."""
    kl_target: float = 0.01
    """Target KL for the adaptive β: β ×= 1.5 above 2·target, β ×= 0.5 below target/2."""
    vf_loss_coeff: float = 1.0
    """Weight c_v of the value loss."""
    vf_clip_param: float = 1e5
    """``value_clip="squared"``: clamp of the squared value error (paper: 1e5, i.e. off). ``"ppo2"``: clip range of V
    around the rollout's V."""
    entropy_coeff: float = 0.0
    """Weight c_e of the entropy bonus."""
    num_sgd_iter: int = 30
    """SGD passes over the train batch per epoch (RLlib default 30; paper: volume 50, locomotion 10)."""
    sgd_minibatch_size: int = 128
    """Samples per minibatch; each pass reshuffles and uses ⌊B / size⌋ minibatches (the tail is dropped)."""
    rollout_steps: int = 100
    """Steps T collected from every environment per epoch (train batch = T·N)."""
    grad_clip: float | None = None
    """Max global gradient norm; None = no clipping (paper)."""
    seed: int = 0
    """Seeds the policy-sampling/shuffling generator and ``env.reset``."""
    device: str | None = None
    """Device of the policy and the rollout storage; None = the env's device."""
    advantage_norm: str = "batch"
    """"batch": standardise advantages once over the train batch (paper); "minibatch": per minibatch; "none"."""
    value_clip: str = "squared"
    """"squared": min((V − G)², vf_clip_param) (RLlib); "ppo2": max of the plain and the clipped-V squared error."""
    lr_schedule: str = "constant"
    """"constant", or "linear": lr · max(0, 1 − epoch / lr_anneal_epochs)."""
    lr_anneal_epochs: int = 500
    """Epochs over which the "linear" schedule anneals the lr to 0."""
    adam_eps: float = 1e-8
    """Adam's ε (torch's default 1e-8; CleanRL 1e-5)."""
    fused_adam: bool = False
    """Adam as one fused kernel (CPU or GPU): ≈ 30 % faster steps of small networks, the same update up to float
    rounding (not bit-identical to the default multi-tensor Adam, which is). Off for the paper."""
    compile: bool = False
    """Hand the minibatch loss (:func:`minibatch_loss`: the policy's forward pass, the losses and, through autograd,
    their backward) to ``torch.compile``. For long runs of small networks on the CPU, where each of a minibatch's
    ≈ 100 operations costs more than its arithmetic: a few seconds of compiling at the first update, then a 500k-step
    CleanRL-preset HalfCheetah run 4–13 % shorter (``docs/ppo.md``). Other rounding than eager; needs a C++ compiler.
    Off by default."""
    obs_norm: bool = False
    """Normalise observations by their running mean/variance (over all envs, updated every step), clipped to
    ±``obs_clip``; the statistics are saved in checkpoints and applied by ``act``. Off for the paper."""
    obs_clip: float = 10.0
    """Clip of the normalised observations (``obs_norm``)."""
    reward_norm: bool = False
    """Divide the rewards PPO trains on by the running std of each env's discounted return, clipped to
    ±``reward_clip`` (Gymnasium's ``NormalizeReward``, SB3's ``VecNormalize``); episode statistics stay raw. Off for
    the paper."""
    reward_clip: float = 10.0
    """Clip of the scaled rewards (``reward_norm``)."""
    eval_every: int = 0
    """Every this many epochs run ``eval_episodes`` deterministic episodes on the ``eval_env`` given to PPO and
    report ``eval_return`` (logged as ``charts/eval_return``); 0 = off."""
    eval_episodes: int = 10
    """Episodes per evaluation, spread over the eval env's environments."""

    def __post_init__(self) -> None:
        self.validate("PPOConfig")

    @classmethod
    def cleanrl(cls, **overrides: Any) -> PPOConfig:
        """CleanRL's ``ppo_continuous_action`` defaults (:data:`CLEANRL_PRESET`) with ``overrides`` on top."""
        return cls(**{**CLEANRL_PRESET, **overrides})

    def validate(self, key: str) -> None:
        """Raise ``ValueError`` naming ``<key>.<field>`` for the first value outside its range."""
        for name in ("lr", "clip_param", "vf_clip_param", "kl_target", "adam_eps", "obs_clip", "reward_clip"):
            value = getattr(self, name)
            require(is_number(value) and value > 0, f"{key}.{name}", "> 0", value)
        for name in ("gamma", "gae_lambda"):
            value = getattr(self, name)
            require(is_number(value) and 0.0 <= value <= 1.0, f"{key}.{name}", "in [0, 1]", value)
        for name in ("kl_coeff", "vf_loss_coeff", "entropy_coeff"):
            value = getattr(self, name)
            require(is_number(value) and value >= 0.0, f"{key}.{name}", ">= 0", value)
        for name in ("num_sgd_iter", "sgd_minibatch_size", "rollout_steps", "lr_anneal_epochs", "eval_episodes"):
            require(is_int(getattr(self, name), 1), f"{key}.{name}", "an int >= 1", getattr(self, name))
        require(is_int(self.eval_every, 0), f"{key}.eval_every", "an int >= 0 (0 = off)", self.eval_every)
        for name in ("obs_norm", "reward_norm", "fused_adam", "compile"):
            require(isinstance(getattr(self, name), bool), f"{key}.{name}", "true or false", getattr(self, name))
        require(self.grad_clip is None or (is_number(self.grad_clip) and self.grad_clip > 0), f"{key}.grad_clip",
                "None or > 0", self.grad_clip)
        require(is_int(self.seed, -(2**63)), f"{key}.seed", "an int", self.seed)
        require(self.advantage_norm in ADVANTAGE_NORMS, f"{key}.advantage_norm", f"one of {ADVANTAGE_NORMS}", self.advantage_norm)
        require(self.value_clip in VALUE_CLIP_MODES, f"{key}.value_clip", f"one of {VALUE_CLIP_MODES}", self.value_clip)
        require(self.lr_schedule in LR_SCHEDULES, f"{key}.lr_schedule", f"one of {LR_SCHEDULES}", self.lr_schedule)
        if self.device is not None:
            try:
                torch.device(self.device)
            except (RuntimeError, TypeError) as e:
                raise ValueError(f"{key}.device must be None or a torch device string, got {self.device!r}") from e


CLEANRL_PRESET: dict[str, Any] = dict(
    lr=3e-4, adam_eps=1e-5, lr_schedule="linear", lr_anneal_epochs=488,  # anneal over 1M steps / 2048 per epoch
    gamma=0.99, gae_lambda=0.95, rollout_steps=2048, sgd_minibatch_size=64, num_sgd_iter=10,  # 32 minibatches of 2048
    clip_param=0.2, kl_coeff=0.0, value_clip="ppo2", vf_clip_param=0.2, vf_loss_coeff=0.25,  # 0.5 · ½(V − G)²
    entropy_coeff=0.0, grad_clip=0.5, advantage_norm="minibatch", obs_norm=True, obs_clip=10.0, reward_norm=True,
    reward_clip=10.0, seed=1, fused_adam=True,
)
"""CleanRL's ``ppo_continuous_action.py`` defaults in PPOConfig's terms (one env × 2048 steps per epoch; with N envs
set ``rollout_steps`` = 2048 / N and ``lr_anneal_epochs`` = total steps / 2048 to keep its batch and schedule).
Its value loss ``vf_coef · ½ · max((V − G)², (V_clip − G)²)`` is ``vf_loss_coeff = 0.25`` with the PPO2 clip at
ε = 0.2. One difference is left: CleanRL divides minibatch advantages by the sample std + 1e-8, freeform by the
population std (a factor √(63/64) at 64 samples). Use it with ``MLPActorCritic`` (orthogonal init, state-independent
log σ) and actions clipped by the env (``freeform.envs.from_gymnasium`` clips)."""


class Logger(Protocol):
    def log(self, stats: dict[str, float], step: int) -> None: ...


# ---------------------------------------------------------------------------------------------------------------
# The algorithm's pieces, as small pure functions.
# ---------------------------------------------------------------------------------------------------------------

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def gaussian_log_prob(actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log N(actions; mean, exp(log_std)) summed over the last dim: ``[..., A]`` → ``[...]``."""
    z = (actions - mean) * torch.exp(-log_std)
    return (-0.5 * z.square() - log_std - LOG_SQRT_2PI).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian, summed over the last dim: ``[..., A]`` → ``[...]``."""
    return (log_std + 0.5 + LOG_SQRT_2PI).sum(-1)


def gaussian_kl(mean0: torch.Tensor, log_std0: torch.Tensor, mean1: torch.Tensor, log_std1: torch.Tensor) -> torch.Tensor:
    """KL(N(mean0, σ0) ‖ N(mean1, σ1)) of diagonal Gaussians, summed over the last dim: ``[..., A]`` → ``[...]``."""
    var_ratio = torch.exp(2.0 * (log_std0 - log_std1))
    mahalanobis = ((mean0 - mean1) * torch.exp(-log_std1)).square()
    return (log_std1 - log_std0 + 0.5 * (var_ratio + mahalanobis) - 0.5).sum(-1)


def discounted_cumsum(
    x: torch.Tensor,
    discount: float,
    starts: torch.Tensor,
    initial: torch.Tensor | None = None,
    reverse: bool = False,
) -> torch.Tensor:
    """``y_t = x_t + discount · y_{t−1}``, restarted where ``starts[t]`` (there ``y_t = x_t``); ``y_{−1} = initial``
    (default 0). ``reverse=True`` runs backwards in time: ``y_t = x_t + discount · y_{t+1}`` unless ``starts[t]``.

    ``x [T, ...]``, ``starts [T, ...]`` bool; ``initial [...]``; returns ``[T, ...]`` in ``x``'s dtype. One
    recurrence for the returns, GAE and the episode sums. Why not a loop over t: with few envs and long rollouts
    (a Gymnasium env, T = 2,048, N = 1) the loop's per-step tensor operations cost more than the rollout's own
    arithmetic. So time is cut into blocks of K steps, each solved at once as ``y = L x`` with
    ``L[i, j] = discount^(i − j)`` where no start lies in ``(j, i]`` (else 0), and only the T / K block ends are
    carried in a loop. K shrinks as the batch grows (``L`` holds T·K·N numbers); at K = 1 it is the plain loop.
    """
    if reverse:
        return discounted_cumsum(x.flip(0), discount, starts.flip(0), initial).flip(0)
    steps, rest = x.shape[0], x.shape[1:]
    width = max(1, x[0].numel())
    block = max(1, min(64, steps, 4096 // width, 2**22 // (steps * width)))  # L: ≤ 4M numbers
    pad = (-steps) % block
    flat_x, flat_starts = x.reshape(steps, width), starts.reshape(steps, width)
    if pad:
        flat_x = torch.cat([flat_x, flat_x.new_zeros(pad, width)])
        flat_starts = torch.cat([flat_starts, flat_starts.new_ones(pad, width)])
    blocks = (steps + pad) // block
    xb = flat_x.reshape(blocks, block, width)
    segment = flat_starts.reshape(blocks, block, width).cumsum(1)  # starts in the block up to and including step i
    i = torch.arange(block, device=x.device)
    lag = (i[:, None] - i[None, :]).to(x.dtype)
    powers = torch.full_like(lag, discount).pow(lag.clamp_min(0))  # discount^(i − j)
    # [blocks, i, j, width]: j ≤ i and no start in (j, i]. Masks select (where), never multiply: a non-finite x
    # must stay in its own run, as in the loop.
    linked = (segment[:, :, None, :] == segment[:, None, :, :]) & (lag >= 0)[None, :, :, None]
    local = torch.where(linked, powers[None, :, :, None] * xb[:, None, :, :], 0.0).sum(2)  # from a zero carry
    carry = torch.where(segment == 0, (discount * torch.full_like(lag[0], discount).pow(i.to(x.dtype)))[None, :, None], 0.0)
    previous = x.new_zeros(width) if initial is None else initial.reshape(width).to(x.dtype)
    out = []
    for b in range(blocks):  # a loop over blocks only: the carry of one block's last step into the next
        y = local[b] + torch.where(carry[b] != 0, carry[b] * previous, 0.0)
        out.append(y)
        previous = y[-1]
    return torch.cat(out)[:steps].reshape(steps, *rest)


def compute_advantages(
    rewards: torch.Tensor,
    values: torch.Tensor,
    dones: torch.Tensor,
    last_value: torch.Tensor,
    gamma: float,
    gae_lambda: float,
    truncated: torch.Tensor | None = None,
    final_values: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE(γ, λ) advantages and value targets of a rollout.

    ``rewards, values, dones``: ``[T, N]`` (``dones[t]`` = the step t ended its episode); ``last_value [N]`` = V of the
    observation after the last step, which bootstraps an episode that the rollout cut. Returns ``(advantages,
    returns)``, both ``[T, N]``, with ``returns = advantages + values``; for λ = 1 the return is the discounted
    return G_t = Σ_i γ^i r_{t+i} (+ γ^(T−t) V(s_T) for a cut episode).

    ``truncated [T, N]`` bool (⊆ ``dones``): the episode was cut by a time limit at step t, not terminated; it is
    bootstrapped with ``final_values[t]`` = V(its last observation), while a terminated one is not. The recursion
    stops at every done either way. None (the design env: episodes never truncate) = no step is truncated.
    """
    dones = dones.to(torch.bool)
    next_values = torch.cat([values[1:], last_value.to(values.dtype)[None]])
    bootstrap = torch.where(dones, 0.0, next_values)  # V(s_t+1), or 0 where the episode ended at t …
    if truncated is not None and final_values is not None:
        bootstrap = bootstrap + truncated.to(rewards.dtype) * final_values  # … unless a time limit cut it: V(s_final)
    deltas = rewards + gamma * bootstrap - values
    advantages = discounted_cumsum(deltas, gamma * gae_lambda, dones, reverse=True)
    return advantages, advantages + values


def standardize(x: torch.Tensor, min_std: float = 1e-4) -> torch.Tensor:
    """(x − mean) / max(std, min_std) with the population std, as RLlib's ``standardize_fields``."""
    return (x - x.mean()) / x.std(correction=0).clamp_min(min_std)


def clipped_surrogate(ratio: torch.Tensor, advantages: torch.Tensor, clip_param: float) -> torch.Tensor:
    """PPO's per-sample objective (to maximise): min(A·ρ, A·clip(ρ, 1 − ε, 1 + ε))."""
    return torch.minimum(advantages * ratio, advantages * ratio.clamp(1.0 - clip_param, 1.0 + clip_param))


def clamped_value_loss(values: torch.Tensor, returns: torch.Tensor, vf_clip_param: float) -> torch.Tensor:
    """RLlib's per-sample value loss: min((V − G)², vf_clip_param)."""
    return (values - returns).square().clamp(max=vf_clip_param)


def ppo2_value_loss(
    values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor, vf_clip_param: float
) -> torch.Tensor:
    """PPO2's per-sample value loss: max((V − G)², (V_old + clip(V − V_old, ±c) − G)²)."""
    clipped = old_values + (values - old_values).clamp(-vf_clip_param, vf_clip_param)
    return torch.maximum((values - returns).square(), (clipped - returns).square())


def update_kl_coeff(kl_coeff: float, mean_kl: float, kl_target: float) -> float:
    """RLlib's adaptive KL rule: β ×= 1.5 if KL > 2·target, β ×= 0.5 if KL < target / 2, else unchanged."""
    if mean_kl > 2.0 * kl_target:
        return kl_coeff * 1.5
    if mean_kl < 0.5 * kl_target:
        return kl_coeff * 0.5
    return kl_coeff


def explained_variance(predicted: torch.Tensor, target: torch.Tensor) -> float:
    """1 − Var(target − predicted) / Var(target); NaN when the target is constant."""
    var = target.var(correction=0)
    return float("nan") if var.item() == 0 else (1.0 - (target - predicted).var(correction=0) / var).item()


def minibatch_samples(
    actions: torch.Tensor,
    old_means: torch.Tensor,
    old_log_stds: torch.Tensor,
    old_logprobs: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
) -> torch.Tensor:
    """The rollout's per-sample floats side by side, ``[B, 3A + 3]``: actions, π_old's means and log σ (``[B, A]``
    each), the old log-probability, the old value and the return (``[B]`` each) — the layout ``minibatch_loss``
    reads. One tensor, so a minibatch is one gather instead of six (≈ 10 µs each at 64 samples on the CPU)."""
    return torch.cat([actions, old_means, old_log_stds, old_logprobs[:, None], old_values[:, None], returns[:, None]],
                     dim=1)


def minibatch_loss(
    policy: nn.Module,
    cfg: PPOConfig,
    obs: torch.Tensor,
    samples: torch.Tensor,
    advantages: torch.Tensor,
    kl_coeff: torch.Tensor | None,
    reduce: Callable[[torch.Tensor], torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO's loss on one minibatch of M samples, and its statistics.

    ``obs [M, ...]`` as the policy saw them; ``samples [M, 3A + 3]`` those samples' rows of
    :func:`minibatch_samples`; ``advantages [M]`` (standardised as ``cfg.advantage_norm`` says); ``kl_coeff`` β as a
    0-d tensor, None without the KL penalty; ``reduce`` the minibatch mean (``Collectives.minibatch_mean``).
    Returns ``(loss, stats [6])``: stats are the policy loss, value loss, KL(π_old ‖ π), entropy, clip fraction and
    loss, detached. A pure function of its inputs, so that ``PPOConfig.compile`` can hand it to ``torch.compile``.
    """
    a = (samples.shape[1] - 3) // 3
    actions, old_means, old_log_stds, old_logprobs, old_values, returns = samples.split([a, a, a, 1, 1, 1], dim=1)
    old_logprobs, old_values, returns = old_logprobs.squeeze(1), old_values.squeeze(1), returns.squeeze(1)
    mean, log_std, value = policy(obs)
    ratio = torch.exp(gaussian_log_prob(actions, mean, log_std) - old_logprobs)
    policy_loss = -reduce(clipped_surrogate(ratio, advantages, cfg.clip_param))
    if cfg.value_clip == "squared":
        value_loss = reduce(clamped_value_loss(value, returns, cfg.vf_clip_param))
    else:
        value_loss = reduce(ppo2_value_loss(value, old_values, returns, cfg.vf_clip_param))
    entropy = reduce(gaussian_entropy(log_std))
    loss = policy_loss + cfg.vf_loss_coeff * value_loss - cfg.entropy_coeff * entropy
    with torch.set_grad_enabled(kl_coeff is not None):  # without the penalty the KL is only a statistic
        kl = reduce(gaussian_kl(old_means, old_log_stds, mean, log_std))
    if kl_coeff is not None:
        loss = loss + kl_coeff * kl
    with torch.no_grad():
        clip_fraction = reduce(((ratio - 1.0).abs() > cfg.clip_param).float())
        stats = torch.stack([policy_loss, value_loss, kl, entropy, clip_fraction, loss])
    return loss, stats


# ---------------------------------------------------------------------------------------------------------------
# Rollout storage.
def _own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with a code object of its own. torch.compile keeps its compiled graphs per code object, and each PPO's
    graph guards on its own policy, so PPO instances sharing ``minibatch_loss``'s code would recompile one another
    and, past ``torch._dynamo.config.recompile_limit`` (8) in one process (a sweep, a test suite), silently run
    eager; with its own code each instance compiles once."""
    copy = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__, copy.__doc__ = fn.__kwdefaults__, fn.__doc__
    return copy


# ---------------------------------------------------------------------------------------------------------------


@dataclass
class Rollout:
    """One epoch's samples, on the PPO device. Observations keep the env's dtype (uint8 grids stay uint8).

    ``obs [T, N, *obs_shape]``, ``actions [T, N, A]``, ``logprobs [T, N]``, ``rewards [T, N]``, ``dones [T, N]``
    bool, ``values [T, N]``, ``means``/``log_stds [T, N, A]`` (π_old, for the KL term), ``advantages``/``returns
    [T, N]`` (filled after collection), ``last_value [N]`` (V of the observation after the last step).
    ``truncated [T, N]`` bool (the env's ``info["truncated"]``: ended by a time limit) and ``final_values [T, N]``
    (V of such an episode's last observation, its bootstrap); ``valid [T, N]`` bool (False where the env only reset,
    ``info["autoreset"]``: such samples never enter the loss). ``obs`` holds what the policy saw (normalised, with
    ``obs_norm``) and ``rewards`` what it trained on (scaled, with ``reward_norm``). ``episode_returns [T, N]``: each
    env's raw episode return so far (carried across rollouts); at a done step it is the finished episode's return,
    the one figure that TensorBoard, the console, the design records and the renders all read.
    PPO refills these tensors every epoch (``logprobs``, ``values``, ``rewards`` and the advantages may be replaced
    by new ones): clone what must outlive the next ``train_epoch()``.
    """

    obs: torch.Tensor
    actions: torch.Tensor
    logprobs: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    values: torch.Tensor
    means: torch.Tensor
    log_stds: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor
    last_value: torch.Tensor
    truncated: torch.Tensor
    final_values: torch.Tensor
    valid: torch.Tensor
    episode_returns: torch.Tensor

    def __getitem__(self, name: str) -> torch.Tensor:
        """Dict-style access, ``rollout["obs"]``."""
        return getattr(self, name)

    @classmethod
    def allocate(
        cls, steps: int, num_envs: int, obs_shape: tuple[int, ...], obs_dtype: torch.dtype, action_dim: int, device: torch.device
    ) -> Rollout:
        f32 = dict(dtype=torch.float32, device=device)
        return cls(
            obs=torch.zeros((steps, num_envs, *obs_shape), dtype=obs_dtype, device=device),
            actions=torch.zeros((steps, num_envs, action_dim), **f32),
            logprobs=torch.zeros((steps, num_envs), **f32),
            rewards=torch.zeros((steps, num_envs), **f32),
            dones=torch.zeros((steps, num_envs), dtype=torch.bool, device=device),
            values=torch.zeros((steps, num_envs), **f32),
            means=torch.zeros((steps, num_envs, action_dim), **f32),
            log_stds=torch.zeros((steps, num_envs, action_dim), **f32),
            advantages=torch.zeros((steps, num_envs), **f32),
            returns=torch.zeros((steps, num_envs), **f32),
            last_value=torch.zeros((num_envs,), **f32),
            truncated=torch.zeros((steps, num_envs), dtype=torch.bool, device=device),
            final_values=torch.zeros((steps, num_envs), **f32),
            valid=torch.ones((steps, num_envs), dtype=torch.bool, device=device),
            episode_returns=torch.zeros((steps, num_envs), **f32),
        )


# ---------------------------------------------------------------------------------------------------------------
# PPO.
# ---------------------------------------------------------------------------------------------------------------


class PPO:
    """Proximal policy optimisation over a batched environment (``freeform.envs.VecEnv``).

    After ``train_epoch()`` the caller may read ``rollout`` (the epoch's ``Rollout``) and ``episode_infos`` (the
    ``info`` dicts of the epoch's steps where any env finished an episode, in order). ``global_step`` counts env steps
    over all envs, ``epoch`` the epochs trained, ``kl_coeff`` is the current β.

    ``dp`` holds the collectives (``distributed.Collectives``; the identity in one process). Data-parallel when a
    process group of several ranks exists at construction: ``env`` is this rank's slice of the environments (slices
    contiguous in rank order), ``dp`` is a ``DataParallel``, ``num_envs`` is the global count;
    ``rollout``/``episode_infos`` stay local (``dp.gather_rollout`` gives the global view), statistics,
    ``global_step``, ``state_dict()`` and checkpoints are global. Every rank must call ``train_epoch``,
    ``state_dict``, ``save`` and ``load`` (collectives); only rank 0 writes the file.
    """

    def __init__(
        self,
        env: VecEnv,
        policy: nn.Module,
        config: PPOConfig | None = None,
        logger: Logger | None = None,
        eval_env: VecEnv | None = None,
    ):
        self.config = config = config if config is not None else PPOConfig()
        if not isinstance(config, PPOConfig):
            raise ValueError(f"config must be a PPOConfig, got {type(config).__name__}")
        for attr in ("num_envs", "observation_shape", "action_dim", "reset", "step"):
            if not hasattr(env, attr):
                raise ValueError(f"env must follow freeform.envs.VecEnv; it has no {attr!r}")
        self.env = env
        self.device = torch.device(config.device) if config.device is not None else torch.device(env.device)
        self.policy = policy.to(self.device)
        self.logger = logger
        self.dp = distributed.collectives(env.num_envs, self.device)
        self.dp.broadcast_module_(self.policy)  # identical starting weights, whatever each rank's RNG did
        self.num_envs = self.dp.num_envs
        """N, environments over all ranks (= ``env.num_envs`` in one process)."""
        self.critic_apart = all(callable(getattr(policy, name, None)) for name in ("action_params", "value"))
        """The policy has ``action_params``/``value`` (actor and critic share nothing): the rollout runs the actor per
        step and the critic once over the rollout (``networks.py``)."""
        self.flat = FlatParameters(self.policy.parameters())
        """The policy's trainable parameters as views of one tensor (``flat.value``), gradients of another: Adam,
        clipping and zeroing are one operation each (``flat_params.py``)."""
        impl = {"fused": True} if config.fused_adam else {"foreach": True}
        self.optimizer = torch.optim.Adam([self.flat.value], lr=config.lr, eps=config.adam_eps, **impl)
        self._minibatch_loss = torch.compile(_own_code(minibatch_loss), dynamic=False) if config.compile else minibatch_loss
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.kl_coeff = float(config.kl_coeff)
        self.epoch = 0
        self.global_step = 0

        self.eval_env = eval_env
        """Where ``evaluate`` runs (every ``config.eval_every`` epochs); None = no evaluation."""
        self._eval_seeded = False
        # Running statistics of the optional normalisations (None when off, the paper's case).
        obs_shape = tuple(env.observation_shape)
        self.obs_rms = RunningMeanStd(obs_shape, self.device) if config.obs_norm else None
        self.return_rms = RunningMeanStd((), self.device) if config.reward_norm else None
        # float64 as the statistics (Gymnasium's too); only with reward_norm, as no float64 may exist (MPS)
        self.discounted_return = torch.zeros(env.num_envs, dtype=torch.float64 if config.reward_norm else torch.float32,
                                             device=self.device)
        """Each env's discounted return of raw rewards, whose running std scales the rewards (``reward_norm``)."""

        self.obs = env.reset(seed=config.seed).to(self.device)
        self._update_obs_rms(self.obs)
        self._check_policy()
        obs_dtype = torch.float32 if self.obs_rms is not None else self.obs.dtype
        self.rollout = Rollout.allocate(config.rollout_steps, env.num_envs, obs_shape, obs_dtype, env.action_dim, self.device)
        self.episode_infos: list[dict[str, Any]] = []
        self._collector = EpisodeCollector()  # episodes() cuts the rollouts; its carry is part of the state
        self._collected = 0  # the epoch count at the last episodes() call
        # Running return and length of each env's current episode (they span epochs when episodes are cut).
        self.episode_return = torch.zeros(env.num_envs, dtype=torch.float32, device=self.device)
        self.episode_length = torch.zeros(env.num_envs, dtype=torch.int64, device=self.device)

    @torch.no_grad()
    def _check_policy(self) -> None:
        """Fail early, naming the mismatch, when the policy's outputs do not fit the env."""
        n, a = self.env.num_envs, self.env.action_dim
        try:
            outputs = self.policy(self.normalize_obs(self.obs))
        except Exception as e:
            raise ValueError(f"policy cannot read the env's observations {tuple(self.obs.shape)} ({e})") from e
        shapes = [tuple(x.shape) for x in outputs] if isinstance(outputs, tuple) and len(outputs) == 3 else None
        if shapes != [(n, a), (n, a), (n,)]:
            raise ValueError(
                f"policy must return (mean [{n}, {a}], log_std [{n}, {a}], value [{n}]) for this env, got {shapes}"
            )
        if self.critic_apart:  # the rollout calls the halves: they must be forward's
            seen = self.normalize_obs(self.obs)
            halves = (*self.policy.action_params(seen), self.policy.value(seen))
            if [tuple(x.shape) for x in halves] != shapes or not all(
                torch.allclose(h, o) for h, o in zip(halves, outputs, strict=True)
            ):
                raise ValueError("policy.action_params(obs) and policy.value(obs) must give what forward(obs) gives "
                                 f"((mean, log_std) and value, shapes {shapes})")

    # -- acting ----------------------------------------------------------------------------------------------------

    def _sample(
        self, obs: torch.Tensor, deterministic: bool = False, noise: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, ...]:
        """obs ``[N, ...]`` → (action, value, mean, log_std); ``noise [N, A]`` ~ N(0, 1), else drawn from
        ``self.generator``. ``value`` is None when the critic runs apart (``critic_apart``)."""
        if self.critic_apart:
            (mean, log_std), value = self.policy.action_params(obs), None
        else:
            mean, log_std, value = self.policy(obs)
        if deterministic:
            return mean, value, mean, log_std
        if noise is None:
            noise = self.dp.env_noise(mean, self.generator)
        return torch.addcmul(mean, torch.exp(log_std), noise), value, mean, log_std

    def _value(self, obs: torch.Tensor) -> torch.Tensor:
        """V(obs) ``[N]`` for observations as the policy sees them."""
        return self.policy.value(obs) if self.critic_apart else self.policy(obs)[2]

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        """Actions ``[N, A]`` for raw observations ``[N, ...]`` (the mean if ``deterministic``), on the env's device.

        With ``obs_norm`` the observations are normalised by the saved statistics (not updated). Sampling draws from
        the training generator, so calls between epochs shift the training's random stream.
        """
        x = self.normalize_obs(obs.to(self.device))
        return self._sample(x, deterministic)[0].to(self.env.device)

    def normalize_obs(self, obs: torch.Tensor) -> torch.Tensor:
        """What the policy sees: ``obs`` itself, or with ``obs_norm`` ``clip((obs − μ) / √(σ² + 1e-8), ±obs_clip)``."""
        if self.obs_rms is None:
            return obs
        return self.obs_rms.normalize(obs, self.config.obs_clip)

    def _update_obs_rms(self, obs: torch.Tensor) -> None:
        if self.obs_rms is not None:
            obs, shape = self.dp.gather_envs(obs), self.obs_rms.mean.shape  # every rank's envs
            self.obs_rms.update(obs if obs.shape[1:] == shape else obs.reshape(-1, *shape))

    def _scale_rewards(self, rewards: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """``reward_norm``: the rollout's rewards ``[T, N]`` divided by √(Var[discounted return] + 1e-8), clipped.

        Step t reads the variance after the returns of steps ≤ t were folded in, as a per-step update would
        (Gymnasium's ``NormalizeReward``); each env's discounted return restarts where ``starts`` (its episode began)
        and carries over between rollouts in ``self.discounted_return``.
        """
        if self.return_rms is None:
            return rewards
        returns = discounted_cumsum(rewards.double(), self.config.gamma, starts, self.discounted_return)
        var = self.return_rms.update_steps(self.dp.gather_envs(returns, dim=1))  # every rank's envs, step by step
        self.discounted_return = returns[-1]
        scale = torch.rsqrt(var + 1e-8).to(rewards.dtype)
        return (rewards * scale[:, None]).clamp(-self.config.reward_clip, self.config.reward_clip)

    # -- rollout ---------------------------------------------------------------------------------------------------

    @torch.no_grad()
    def collect(self) -> dict[str, float]:
        """Step every env ``rollout_steps`` times with the current policy into ``self.rollout``; fill advantages."""
        cfg, buf = self.config, self.rollout
        self.episode_infos = []
        time_env = 0.0
        any_truncated = False
        buf.truncated.zero_()
        buf.final_values.zero_()
        buf.valid.fill_(True)
        self.policy.eval()
        # Each step's tensors are listed and stacked into the buffers once, after the loop; what needs no policy
        # (log-probabilities, reward scaling, episode sums) is computed there for the whole rollout. With one env
        # (a Gymnasium task) every tensor operation in this loop costs more than its arithmetic.
        seen, actions, values, means, log_stds, rewards, dones = [], [], [], [], [], [], []
        scored: list[tuple[int, torch.Tensor]] = []  # (step, the task's own score of the episodes ending there)
        # The whole rollout's noise in one draw, in the rollout's dtype (float32). On the CPU T draws of N·A values
        # equal one of T·N·A where N·A is a multiple of 16 (the design env's sizes); otherwise the stream differs.
        noise = self.dp.env_noise(buf.actions, self.generator)
        # The env's tensors are moved or cast only where they need it: even a no-op .to() is an operation.
        env_device = self.env.device
        here = env_device is not None and torch.device(env_device) == self.device
        for t in range(cfg.rollout_steps):
            x = self.normalize_obs(self.obs)
            action, value, mean, log_std = self._sample(x, noise=noise[t])
            for store, item in ((seen, x), (actions, action), (values, value), (means, mean), (log_stds, log_std)):
                store.append(item)  # (values: None when the critic runs apart, after the loop)
            t0 = time.perf_counter()
            next_obs, reward, done, info = self.env.step(action if here else action.to(env_device))
            time_env += time.perf_counter() - t0
            if not here or reward.dtype != torch.float32:
                reward = reward.to(self.device, torch.float32)
            if not here or done.dtype != torch.bool:
                done = done.to(self.device, torch.bool)
            if not here:
                next_obs = next_obs.to(self.device)
            if next_obs.data_ptr() == self.obs.data_ptr():
                raise ValueError("env.step returned the observation tensor of the previous step, written in place: a "
                                 "VecEnv must return new tensors (PPO keeps every step's until the rollout ends)")
            self._update_obs_rms(next_obs)
            rewards.append(reward)
            dones.append(done)
            if "autoreset" in info:  # the env only reset (Gymnasium's next-step autoreset): not a transition
                buf.valid[t] = ~info["autoreset"].to(self.device, torch.bool)
            if done.any():
                self.episode_infos.append(info)
                if "task_reward" in info:  # shaped rewards (dense_every): the return is what the task scored
                    scored.append((t, info["task_reward"]))
                if "truncated" in info:  # a time limit, not a terminal state: bootstrap with V(last observation)
                    truncated = info["truncated"].to(self.device, torch.bool)
                    if truncated.any():
                        any_truncated = True
                        buf.truncated[t] = truncated
                        final_value = self._value(self.normalize_obs(info["final_obs"].to(self.device)))
                        buf.final_values[t] = torch.where(truncated, final_value, 0.0)
            self.obs = next_obs
        for name, steps in (("obs", seen), ("actions", actions), ("means", means), ("log_stds", log_stds),
                            ("rewards", rewards), ("dones", dones)):
            torch.stack(steps, out=buf[name])
        if self.critic_apart:
            buf.values = self._value(buf.obs.reshape(-1, *buf.obs.shape[2:])).reshape(buf.values.shape)
        else:
            torch.stack(values, out=buf.values)
        buf.logprobs = gaussian_log_prob(buf.actions, buf.means, buf.log_stds)
        starts = torch.cat([torch.zeros_like(buf.dones[:1]), buf.dones[:-1]])  # an episode begins after a done

        # Episode figures from the raw rewards (an episode may span rollouts: the sums carry over), computed here only.
        episode_returns = discounted_cumsum(buf.rewards, 1.0, starts, self.episode_return)
        for t, score in scored:
            episode_returns[t] = torch.where(buf.dones[t], score.to(self.device, torch.float32), episode_returns[t])
        buf.episode_returns = episode_returns
        episode_lengths = discounted_cumsum(buf.valid.float(), 1.0, starts, self.episode_length)  # exact < 2²⁴
        returns, lengths = episode_returns[buf.dones], episode_lengths[buf.dones].round().long()
        last_done = buf.dones[-1]
        self.episode_return = torch.where(last_done, 0.0, episode_returns[-1]).to(self.episode_return.dtype)
        self.episode_length = torch.where(last_done, 0.0, episode_lengths[-1]).round().to(self.episode_length.dtype)

        buf.rewards = self._scale_rewards(buf.rewards, starts)
        if self.return_rms is not None:
            self.discounted_return = torch.where(last_done, 0.0, self.discounted_return)
        # An episode that the rollout cut is bootstrapped with V of its last observation.
        buf.last_value = self._value(self.normalize_obs(self.obs))
        buf.advantages, buf.returns = compute_advantages(
            buf.rewards, buf.values, buf.dones, buf.last_value, cfg.gamma, cfg.gae_lambda,
            *((buf.truncated, buf.final_values) if any_truncated else ()),
        )
        self.global_step += cfg.rollout_steps * self.num_envs

        returns, lengths = self.dp.gather_varlen(returns), self.dp.gather_varlen(lengths)  # every rank's episodes
        nan = float("nan")
        return {
            "episode_reward_mean": returns.mean().item() if len(returns) else nan,
            "episode_reward_max": returns.max().item() if len(returns) else nan,
            "episode_reward_min": returns.min().item() if len(returns) else nan,
            "episode_length_mean": lengths.float().mean().item() if len(lengths) else nan,
            "episodes": float(len(returns)),
            "time_env": time_env,
        }

    # -- update ----------------------------------------------------------------------------------------------------

    def current_lr(self) -> float:
        """The learning rate of the coming epoch under ``config.lr_schedule``."""
        cfg = self.config
        if cfg.lr_schedule == "linear":
            return cfg.lr * max(0.0, 1.0 - self.epoch / cfg.lr_anneal_epochs)
        return cfg.lr

    def update(self) -> dict[str, float]:
        """``num_sgd_iter`` passes of minibatch SGD over ``self.rollout``, then the KL-coefficient update.

        Minibatches are drawn from the global batch (``B = T·N`` over all ranks). Data-parallel, every rank draws the
        same permutation, computes the samples of each minibatch it holds (``dp.local_share``) with loss *sums*
        divided by the global minibatch size (``dp.minibatch_mean``), and the gradients are summed over ranks
        (``dp.all_reduce_grad_``): the global minibatch's mean-loss gradient. In one process all three are plain.
        """
        cfg, buf, dp = self.config, self.rollout, self.dp
        batch = buf.rewards.numel()  # this rank's samples
        obs = buf.obs.reshape(batch, *buf.obs.shape[2:])
        actions, old_means, old_log_stds = (x.reshape(batch, -1) for x in (buf.actions, buf.means, buf.log_stds))
        old_logprobs, old_values, returns = buf.logprobs.reshape(-1), buf.values.reshape(-1), buf.returns.reshape(-1)
        # The global batch's advantages (a float per sample) on every rank: standardising over the batch or a
        # minibatch is then the single process's formula on the same numbers.
        advantages = dp.gather_envs(buf.advantages, dim=1).reshape(-1)
        # Samples where an env only reset (Gymnasium's next-step autoreset) are no transitions: they are left out of
        # the minibatches and the batch statistics. ``kept`` = the global indices of the others (None: all of them).
        valid = dp.gather_envs(buf.valid, dim=1).reshape(-1)
        kept = None if bool(valid.all()) else valid.nonzero().squeeze(1)
        global_batch = advantages.numel() if kept is None else kept.numel()
        if cfg.advantage_norm == "batch":
            if kept is None:
                advantages = standardize(advantages)
            else:
                advantages = advantages.clone()
                advantages[kept] = standardize(advantages[kept])

        lr = self.current_lr()
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        kl_coeff = self.kl_coeff
        minibatch = min(cfg.sgd_minibatch_size, global_batch)
        num_minibatches = global_batch // minibatch
        flat = self.flat
        flat.check()

        def reduce(x: torch.Tensor) -> torch.Tensor:
            return dp.minibatch_mean(x, minibatch)

        samples = minibatch_samples(actions, old_means, old_log_stds, old_logprobs, old_values, returns)
        kl_weight = torch.tensor(kl_coeff, device=self.device) if kl_coeff > 0.0 else None
        # Sums over minibatches, kept on the device so that no step waits for a host sync.
        totals = torch.zeros(6, device=self.device)  # policy, value, kl, entropy, clip fraction, total loss
        self.policy.train()
        for _ in range(cfg.num_sgd_iter):
            order = torch.randperm(global_batch, generator=self.generator, device=self.device)
            if kept is not None:
                order = kept[order]
            for i in range(num_minibatches):
                idx = order[i * minibatch : (i + 1) * minibatch]
                adv = advantages[idx]
                if cfg.advantage_norm == "minibatch":
                    adv = standardize(adv)
                idx, adv = dp.local_share(idx, adv)
                flat.zero_grad()
                if idx.numel():  # a rank may hold none of a minibatch; it then adds zero gradients
                    loss, stats = self._minibatch_loss(
                        self.policy, cfg, obs.index_select(0, idx), samples.index_select(0, idx), adv, kl_weight, reduce
                    )
                    loss.backward()
                    totals += stats
                dp.all_reduce_grad_(flat.grad)
                if cfg.grad_clip is not None:
                    flat.clip_grad_norm_(cfg.grad_clip)
                self.optimizer.step()

        dp.sum_(totals)  # each rank summed its shares of the minibatch means: their sum is the global mean
        means = (totals / (cfg.num_sgd_iter * num_minibatches)).tolist()
        mean_kl = means[2]
        # RLlib's rule, on the mean KL over every minibatch update of the epoch (the same number on every rank).
        self.kl_coeff = update_kl_coeff(kl_coeff, mean_kl, cfg.kl_target)
        values, log_stds = dp.gather_envs(buf.values, dim=1), dp.gather_envs(buf.log_stds, dim=1)
        returns = dp.gather_envs(buf.returns, dim=1).reshape(-1)
        values = values.reshape(-1)
        stds = log_stds.exp()
        if kept is not None:
            values, returns, stds = values[kept], returns[kept], stds.reshape(-1, stds.shape[-1])[kept]
        stats = {
            "policy_loss": means[0],
            "value_loss": means[1],
            "approx_kl": mean_kl,
            "entropy": means[3],
            "clip_fraction": means[4],
            "total_loss": means[5],
            "kl_coeff": kl_coeff,
            "lr": lr,
            "explained_variance": explained_variance(values, returns),
            "value_mean": values.mean().item(),
            "action_std": stds.mean().item(),
        }
        for name, dims in getattr(self.policy, "action_groups", {}).items():
            stats[f"action_std_{name}"] = stds[..., dims].mean().item()
        return stats

    # -- the loop --------------------------------------------------------------------------------------------------

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def train_epoch(self) -> dict[str, float]:
        """Collect ``rollout_steps`` steps from every env, update the policy; return the epoch's statistics."""
        t0 = time.perf_counter()
        stats = self.collect()
        self._sync()
        t1 = time.perf_counter()
        stats.update(self.update())
        self._sync()
        t2 = time.perf_counter()
        self.epoch += 1
        samples = self.config.rollout_steps * self.num_envs
        stats.update(
            time_rollout=t1 - t0,
            time_update=t2 - t1,
            samples_per_second=samples / max(t2 - t0, 1e-9),
            epoch=float(self.epoch),
            global_step=float(self.global_step),
        )
        if self.config.eval_every and self.eval_env is not None and self.epoch % self.config.eval_every == 0:
            stats.update(self.evaluate())
        if self.logger is not None:
            self.logger.log(stats, self.global_step)
        return stats

    @torch.no_grad()
    def evaluate(self, env: VecEnv | None = None, episodes: int | None = None) -> dict[str, float]:
        """Deterministic episodes (the policy's mean action) on ``env`` (default ``self.eval_env``), never the
        training env: ``eval_return`` (mean raw return), ``eval_return_std``, ``eval_length_mean``.

        ``episodes`` (default ``config.eval_episodes``) are spread over the env's environments as evenly as possible
        (env i runs ⌈(episodes − i) / n⌉ of them, as SB3's ``evaluate_policy``), so short episodes are not favoured.
        The env is reset first (seeded ``config.seed + 1`` the first time); the training generator draws nothing and
        observation statistics are applied, not updated. Data-parallel, each rank evaluates its own eval env and
        the figures are over every rank's episodes.
        """
        env = self.eval_env if env is None else env
        if env is None:
            raise ValueError("evaluate needs an env: pass one, or eval_env to PPO")
        episodes = self.config.eval_episodes if episodes is None else episodes
        n = env.num_envs
        targets = torch.tensor([(episodes + n - 1 - i) // n for i in range(n)], device=self.device)
        counts = torch.zeros(n, dtype=torch.int64, device=self.device)
        returns, lengths = [], []
        seed = None if self._eval_seeded else self.config.seed + 1
        self._eval_seeded = True
        obs = env.reset(seed=seed).to(self.device)
        ep_return = torch.zeros(n, device=self.device)
        ep_length = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.policy.eval()
        while bool((counts < targets).any()):
            mean = self._sample(self.normalize_obs(obs), deterministic=True)[0]
            obs, reward, done, info = env.step(mean.to(env.device))
            obs, reward, done = obs.to(self.device), reward.to(self.device, torch.float32), done.to(self.device, torch.bool)
            moving = ~info["autoreset"].to(self.device, torch.bool) if "autoreset" in info else torch.ones_like(done)
            ep_return += reward
            ep_length += moving.to(ep_length.dtype)
            wanted = done & (counts < targets)
            if wanted.any():
                returns.append(ep_return[wanted])
                lengths.append(ep_length[wanted])
            counts += done.to(counts.dtype)
            ep_return = torch.where(done, 0.0, ep_return)
            ep_length = torch.where(done, 0, ep_length)
        all_returns = self.dp.gather_varlen(torch.cat(returns))
        all_lengths = self.dp.gather_varlen(torch.cat(lengths))
        return {
            "eval_return": all_returns.mean().item(),
            "eval_return_std": all_returns.std(correction=0).item(),
            "eval_length_mean": all_lengths.float().mean().item(),
        }

    def learn(self, epochs: int, callback: Callable[[PPO, dict[str, float]], bool | None] | None = None) -> list[dict]:
        """Train ``epochs`` epochs; ``callback(ppo, stats)`` runs after each and stops training by returning False."""
        if not isinstance(epochs, int) or epochs < 0:
            raise ValueError(f"epochs must be an int >= 0, got {epochs!r}")
        history = []
        for _ in range(epochs):
            history.append(self.train_epoch())
            if callback is not None and callback(self, history[-1]) is False:
                break
        return history

    def episodes(self) -> Episodes | None:
        """The episodes the last rollout finished, over every rank, in the design records' layout
        (``freeform.learner``; ``None`` if none finished): for envs whose episodes end in lock-step and report
        ``final_grids`` (the design envs). An episode cut by the rollout's end is carried to the next call, so call
        it after every epoch (the trainer does); a collective when data-parallel."""
        if self._collected != self.epoch - 1 and self._collector.state_dict():
            raise ValueError(f"episodes() was not called after epochs {self._collected + 1}..{self.epoch - 1}, and an "
                             "episode spans rollouts: its first steps are gone")
        self._collected = self.epoch
        rollout, infos = self.dp.gather_rollout(self.rollout, self.episode_infos)
        episodes = self._collector.collect(rollout, infos)
        if episodes is not None:
            episodes["infos"] = infos
        return episodes

    # -- state and checkpoints -------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: policy, optimizer, β, counters, RNG, current obs, env state.

        What is per environment is named: it lives under ``per_env`` (``distributed.PER_ENV``; the env's own state
        names its part the same way). Data-parallel: a collective; the per-environment parts are gathered from
        every rank, so the state is the global one — loadable with any number of ranks.
        """
        state = {
            "policy": self.policy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "kl_coeff": self.kl_coeff,
            "epoch": self.epoch,
            "global_step": self.global_step,
            "generator": self.generator.get_state(),
            PER_ENV: {"obs": self.obs, "episode_return": self.episode_return, "episode_length": self.episode_length},
            "episode_carry": self._collector.state_dict(),  # global: cut from the gathered rollout
        }
        if self.obs_rms is not None:
            state["obs_rms"] = self.obs_rms.state_dict()
        if self.return_rms is not None:
            state["return_rms"] = self.return_rms.state_dict()
            state[PER_ENV]["discounted_return"] = self.discounted_return
        if hasattr(self.env, "state_dict"):
            state["env"] = self.env.state_dict()
        return self.dp.gather_state(state)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what ``state_dict()`` returned (the policy and env must be built alike; in a data-parallel run,
        a global state of any rank count: each rank takes its slice of the environments)."""
        saved_envs = state[PER_ENV]["obs"].shape[0]
        if saved_envs != self.num_envs:
            raise ValueError(f"the state holds {saved_envs} envs but this run has {self.num_envs}")
        state = self.dp.shard_state(state)
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(self.flat.optimizer_state(state["optimizer"]))
        self.kl_coeff = float(state["kl_coeff"])
        self.epoch = int(state["epoch"])
        self.global_step = int(state["global_step"])
        self._collected = self.epoch
        self._collector.load_state_dict(state.get("episode_carry", {}))
        self.generator.set_state(state["generator"].cpu())
        per_env = state[PER_ENV]
        self.obs = per_env["obs"].to(self.device)
        self.episode_return = per_env["episode_return"].to(self.device)
        self.episode_length = per_env["episode_length"].to(self.device)
        for name, rms in (("obs_rms", self.obs_rms), ("return_rms", self.return_rms)):
            if rms is not None:
                if name not in state:
                    raise ValueError(f"the config normalises ({name}) but the state holds no {name} statistics")
                rms.load_state_dict(state[name])
        if self.return_rms is not None:
            self.discounted_return = per_env["discounted_return"].to(self.device, torch.float64)
        if "env" in state:
            if not hasattr(self.env, "load_state_dict"):
                raise ValueError("the state holds an env state but the env has no load_state_dict()")
            self.env.load_state_dict(state["env"])

    def checkpoint(self) -> dict[str, Any]:
        """A self-describing checkpoint's content: the policy's class name and constructor arguments, this
        ``PPOConfig`` and the training state (a collective when data-parallel). The trainer's run checkpoints are
        this plus the run's own parts, so :meth:`load` reads both."""
        return {
            "policy_class": policy_class_name(type(self.policy)),
            "policy_kwargs": dict(getattr(self.policy, "init_kwargs", {})),
            "ppo_config": dataclasses.asdict(self.config),
            "epoch": self.epoch,
            "global_step": self.global_step,
            "ppo": self.state_dict(),
        }

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Continue from a checkpoint :meth:`checkpoint` wrote (the ``Learner`` protocol): ``load_state_dict`` of
        its ``ppo`` part."""
        self.load_state_dict(checkpoint["ppo"])

    def save(self, path: str | os.PathLike) -> None:
        """Write :meth:`checkpoint` atomically (``freeform.checkpoint.save_checkpoint``).

        Data-parallel: every rank calls it (the state is gathered); rank 0 writes.
        """
        payload = self.checkpoint()
        if self.dp.is_writer:
            save_checkpoint(path, payload)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        env: VecEnv,
        logger: Logger | None = None,
        device: str | None = None,
        policy_classes: Sequence[type[nn.Module]] = (),
    ) -> PPO:
        """Rebuild a PPO (policy, config, full training state) from a file of :meth:`save` or a run's checkpoint.

        The file names its policy class; it is built only if it is one of freeform's networks or in
        ``policy_classes`` (the caller's own, allowed explicitly): loading never imports what a file names, and the
        file itself is read with ``weights_only`` (no code runs). ``device`` overrides the saved ``config.device``.
        Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file for a corrupt or
        incompatible one.
        """
        payload = load_checkpoint(path)
        allowed = {policy_class_name(c): c for c in (*builtin_policies(), *policy_classes)}
        try:
            name = payload["policy_class"]
            if name not in allowed:
                raise CheckpointError(
                    f"{path}: its policy class {name!r} is not one of freeform's networks; pass "
                    f"policy_classes=[<that class>] to PPO.load to build it"
                )
            policy = allowed[name](**payload["policy_kwargs"])
            config_dict = dict(payload["ppo_config"])
            if device is not None:
                config_dict["device"] = device
            config = PPOConfig(**config_dict)
        except CheckpointError:
            raise
        except Exception as e:
            raise CheckpointError(f"{path}: cannot rebuild the policy/config ({type(e).__name__}: {e})") from e
        state = payload["ppo"]
        saved_obs = state[PER_ENV]["obs"]

        def check_envs(num_envs: int) -> None:
            if saved_obs.shape[0] != num_envs or tuple(saved_obs.shape[1:]) != tuple(env.observation_shape):
                raise CheckpointError(
                    f"{path}: saved for {saved_obs.shape[0]} envs with observations {tuple(saved_obs.shape[1:])}, "
                    f"but the env has {num_envs} envs with observations {tuple(env.observation_shape)}"
                )

        if not distributed.is_distributed():
            check_envs(env.num_envs)
        try:
            ppo = cls(env, policy, config, logger)
        except ValueError as e:
            raise CheckpointError(f"{path}: the saved policy does not fit this env ({e})") from e
        check_envs(ppo.num_envs)  # data-parallel: the global count (a collective in the constructor learnt it)
        try:
            ppo.load_state_dict(state)
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"{path}: incompatible training state ({type(e).__name__}: {e})") from e
        return ppo


def policy_class_name(cls: type) -> str:
    """How a checkpoint names a policy class: ``module:qualname``."""
    return f"{cls.__module__}:{cls.__qualname__}"


def builtin_policies() -> tuple[type[nn.Module], ...]:
    """The networks any checkpoint may name (freeform's own)."""
    from freeform.agents.networks import MLPActorCritic, VoxelActorCritic

    return (VoxelActorCritic, MLPActorCritic)
