"""PPO's mathematics as small pure functions of tensors, each tested against hand-worked values or a reference
(``tests/test_ppo.py``): discounted sums, GAE, the clipped surrogate, the value losses, the adaptive KL rule, and
the whole minibatch loss (:func:`minibatch_loss`, which ``PPOConfig.compile`` hands to
``torch.compile``).

The action distributions' log-probabilities, entropies and KLs live in ``freeform.distributions`` (the
Gaussian's are re-exported here, where they were first).

Shapes: ``T`` = ``rollout_steps``, ``N`` = environments, ``A`` = action size, ``M`` = a minibatch's samples.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn as nn

from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.rollout import Sequences, sample_columns
from freeform.distributions import ActionDistribution, gaussian_entropy, gaussian_kl, gaussian_log_prob


def leave_one_out(rewards: torch.Tensor, groups: torch.Tensor) -> torch.Tensor:
    """Each reward minus the mean of the same step's rewards in its group's other members: ``rewards [T, N]``,
    ``groups [N]`` int64 in ``0 … G−1``, every group of >= 2 members (``PPOConfig.group_baseline``)."""
    count = torch.bincount(groups).to(rewards.dtype)
    total = torch.zeros(rewards.shape[0], len(count), dtype=rewards.dtype, device=rewards.device)
    total.index_add_(1, groups, rewards)
    others = (total[:, groups] - rewards) / (count[groups] - 1)
    return rewards - others


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


def standardize_groups(x: torch.Tensor, groups: torch.Tensor, min_std: float = 1e-4) -> torch.Tensor:
    """Each group's entries standardised by their own mean and population std (:func:`standardize` per group):
    ``x [T, N]``, ``groups [N]`` int64 in ``0 … G−1`` naming each column's group (a group pools its columns over
    every row)."""
    g = groups.expand_as(x).reshape(-1)
    flat = x.reshape(-1)
    count = torch.bincount(g).to(x.dtype)
    mean = torch.zeros_like(count).index_add_(0, g, flat) / count
    centred = flat - mean[g]
    std = (torch.zeros_like(count).index_add_(0, g, centred * centred) / count).sqrt()
    return (centred / std.clamp_min(min_std)[g]).reshape(x.shape)


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


def minibatch_loss(
    policy: nn.Module,
    dist: ActionDistribution,
    cfg: PPOConfig,
    obs: torch.Tensor,
    samples: torch.Tensor,
    advantages: torch.Tensor,
    kl_coeff: torch.Tensor | None,
    reduce: Callable[[torch.Tensor], torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO's loss on one minibatch of M samples, and its statistics.

    ``dist`` the action distribution (``policy(obs)`` returns its parameters, then V); ``obs [M, ...]`` as the
    policy saw them; ``samples [M, A + P + 3]`` those samples' rows of ``minibatch_samples`` (their columns named by
    ``rollout.Samples``); ``advantages [M]`` (standardised as ``cfg.advantage_norm`` says); ``kl_coeff`` β as a 0-d
    tensor, None without the KL penalty; ``reduce`` the minibatch mean (``Collectives.minibatch_mean``).
    Returns ``(loss, stats [6])``: stats are the policy loss, value loss, KL(π_old ‖ π), entropy, clip fraction and
    loss, detached. A pure function of its inputs, so that ``PPOConfig.compile`` can hand it to ``torch.compile``.
    """
    *params, value = policy(obs)
    return ppo_loss(tuple(params), value, dist, cfg, samples, advantages, kl_coeff, reduce)


def sequence_minibatch_loss(
    policy: nn.Module,
    dist: ActionDistribution,
    cfg: PPOConfig,
    sequences: Sequences,
    samples: torch.Tensor,
    advantages: torch.Tensor,
    kl_coeff: torch.Tensor | None,
    count: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`minibatch_loss` for a recurrent policy, on S sequences of L steps (truncated BPTT).

    ``sequences`` the observations ``[L, S, ...]``, the policy's state at each sequence's start, the episode starts
    and the mask of the steps that count (``rollout.Sequences``); ``samples [L·S, A + P + 3]`` and ``advantages
    [L·S]`` in the same (time-major) order. The means are over the masked steps: sums divided by ``count``, the
    masked steps of the whole minibatch (None: these; data-parallel, every rank's)."""
    *params, value, _ = policy(sequences.obs, sequences.state, sequences.episode_start)
    flat = tuple(p.reshape(-1, p.shape[-1]) for p in params)
    weight = sequences.mask.reshape(-1)
    count = (weight.sum() if count is None else count).clamp_min(1).to(value.dtype)
    return ppo_loss(flat, value.reshape(-1), dist, cfg, samples, advantages, kl_coeff, masked_mean(weight, count))


def masked_mean(weight: torch.Tensor, count: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """A sequence minibatch's ``reduce``: a per-step quantity ``[M]`` summed over the steps that count (``weight
    [M]`` bool) and divided by ``count`` (the minibatch's counted steps, every rank's)."""

    def reduce(x: torch.Tensor) -> torch.Tensor:
        return torch.where(weight, x, 0.0).sum() / count

    return reduce


def ppo_loss(
    params: tuple[torch.Tensor, ...],
    value: torch.Tensor,
    dist: ActionDistribution,
    cfg: PPOConfig,
    samples: torch.Tensor,
    advantages: torch.Tensor,
    kl_coeff: torch.Tensor | None,
    reduce: Callable[[torch.Tensor], torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The loss and its statistics from the policy's outputs on M samples: ``params`` (the distribution's, ``[M,
    P_i]`` each) and ``value [M]``; the other arguments as :func:`minibatch_loss`'s."""
    s = sample_columns(samples, dist.action_dim)
    ratio = torch.exp(dist.log_prob(params, s.actions) - s.old_logprobs)
    policy_loss = -reduce(clipped_surrogate(ratio, advantages, cfg.clip_param))
    if cfg.value_clip == "squared":
        value_loss = reduce(clamped_value_loss(value, s.returns, cfg.vf_clip_param))
    else:
        value_loss = reduce(ppo2_value_loss(value, s.old_values, s.returns, cfg.vf_clip_param))
    entropy = reduce(dist.entropy(params))
    loss = policy_loss + cfg.vf_loss_coeff * value_loss - cfg.entropy_coeff * entropy
    with torch.set_grad_enabled(kl_coeff is not None):  # without the penalty the KL is only a statistic
        kl = reduce(dist.kl(dist.split(s.old_params), params))
    if kl_coeff is not None:
        loss = loss + kl_coeff * kl
    with torch.no_grad():
        clip_fraction = reduce(((ratio - 1.0).abs() > cfg.clip_param).float())
        stats = torch.stack([policy_loss, value_loss, kl, entropy, clip_fraction, loss])
    return loss, stats


__all__ = ["clamped_value_loss", "clipped_surrogate", "compute_advantages", "discounted_cumsum", "explained_variance",
           "gaussian_entropy", "gaussian_kl", "gaussian_log_prob", "masked_mean", "minibatch_loss", "ppo2_value_loss",
           "ppo_loss", "sequence_minibatch_loss", "standardize", "update_kl_coeff"]
