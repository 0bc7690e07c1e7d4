"""The update: ``num_sgd_iter`` passes of minibatch Adam over the rollout, then RLlib's KL rule (``update`` =
``_train_batch`` → ``_sgd`` → ``update_kl_coeff`` → ``_update_stats``), as a part of the ``PPO`` class (``ppo.py``).

Shapes: ``B`` = ``T·N`` (this rank's samples), ``A`` the action size, ``P`` the distribution's parameters.
"""

from __future__ import annotations

import types
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
import torch.nn as nn

from freeform.agents.distributed import Collectives
from freeform.agents.networks import GroupedActions
from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.flat_params import FlatParameters
from freeform.agents.ppo.graphed import GraphedMinibatchStep
from freeform.agents.ppo.losses import (
    explained_variance,
    sequence_minibatch_loss,
    standardize,
    standardize_groups,
    update_kl_coeff,
)
from freeform.agents.ppo.rollout import Observation, Rollout, Sequences, chunked, minibatch_samples, obs_map
from freeform.distributions import ActionDistribution, DiagGaussian, MaskedDiagGaussian


class _TrainBatch(NamedTuple):
    """An update's view of the rollout: ``obs [B, ...]`` and ``samples [B, A + P + 3]`` (this rank's), ``advantages``
    of the global batch, ``kept`` (the global indices of real transitions, None: all) and the global sample count."""

    obs: Observation
    samples: torch.Tensor
    advantages: torch.Tensor
    kept: torch.Tensor | None
    size: int


class _SequenceBatch(NamedTuple):
    """A recurrent policy's update view of the rollout: each env's T steps cut into C chunks of L steps (the last
    padded), S = C·N sequences, time-major: ``obs [L, S, ...]``, ``samples [L, S, A + P + 3]``, ``advantages [L, S]``,
    ``starts [L, S]`` bool (the state is reset before such a step), ``mask [L, S]`` bool (the steps that count: not
    padding, not a step where the env only reset), ``state`` the stored state at each chunk's first step
    (``[S, ...]`` each). Sequence s = c·N + n is env n's chunk c. Data-parallel, those are this rank's (N its envs),
    and ``advantages`` and ``counted`` (the mask) the global batch's, ``[L, C·N_global]``."""

    obs: Observation
    samples: torch.Tensor
    advantages: torch.Tensor
    starts: torch.Tensor
    mask: torch.Tensor
    state: tuple[torch.Tensor, ...]
    counted: torch.Tensor


def own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with a code object of its own. torch.compile keeps its compiled graphs per code object, and each PPO's
    graph guards on its own policy, so PPO instances sharing ``minibatch_loss``'s code would recompile one another
    and, past ``torch._dynamo.config.recompile_limit`` (8) in one process (a sweep, a test suite), silently run
    eager; with its own code each instance compiles once."""
    copy = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__, copy.__doc__ = fn.__kwdefaults__, fn.__doc__
    return copy


class MinibatchUpdate:
    """The update half of :class:`freeform.agents.PPO`: what it reads and writes of the PPO is declared here."""

    config: PPOConfig
    policy: nn.Module
    distribution: ActionDistribution
    dp: Collectives
    device: torch.device
    generator: torch.Generator
    flat: FlatParameters
    optimizer: torch.optim.Adam
    rollout: Rollout
    epoch: int
    kl_coeff: float
    _graphed: GraphedMinibatchStep | None
    recurrent: bool
    _minibatch_loss: Callable[..., tuple[torch.Tensor, torch.Tensor]]

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
        cfg = self.config
        batch = self._train_batch()
        lr, kl_coeff = self.current_lr(), self.kl_coeff
        for group in self.optimizer.param_groups:
            if isinstance(group["lr"], torch.Tensor):  # a graph reads it: written in place
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr
        means = self._sgd(batch, kl_coeff)
        # RLlib's rule, on the mean KL over every minibatch update of the epoch (the same number on every rank).
        self.kl_coeff = update_kl_coeff(kl_coeff, means[2], cfg.kl_target)
        return self._update_stats(batch, means, kl_coeff, lr)

    def _train_batch(self) -> _TrainBatch:
        """The rollout flattened to this rank's ``B`` samples, and the global batch's advantages (standardised over
        the batch with ``advantage_norm="batch"``), on every rank: standardising over the batch or a minibatch is
        then the single process's formula on the same numbers."""
        buf, dp = self.rollout, self.dp
        size = buf.rewards.numel()  # this rank's samples
        obs = obs_map(lambda x: x.reshape(size, *x.shape[2:]), buf.obs)
        samples = minibatch_samples(buf.actions.reshape(size, -1), [p.reshape(size, -1) for p in buf.params],
                                    buf.logprobs.reshape(-1), buf.values.reshape(-1), buf.returns.reshape(-1))
        own = buf.advantages
        if self.config.advantage_norm == "group":  # (a group's environments lie on one rank: its own statistics)
            if not bool(buf.valid.all()):
                raise ValueError("agent.advantage_norm=group: an env that autoresets (samples outside the loss) is "
                                 "not supported; use batch or minibatch")
            own = standardize_groups(own, self.reward_groups)
        advantages = dp.gather_envs(own, dim=1).reshape(-1)
        # Samples where an env only reset (Gymnasium's next-step autoreset) are no transitions: they are left out of
        # the minibatches and the batch statistics. ``kept`` = the global indices of the others (None: all of them).
        valid = dp.gather_envs(buf.valid, dim=1).reshape(-1)
        kept = None if bool(valid.all()) else valid.nonzero().squeeze(1)
        if self.config.advantage_norm == "batch":
            if kept is None:
                advantages = standardize(advantages)
            else:
                advantages = advantages.clone()
                advantages[kept] = standardize(advantages[kept])
        return _TrainBatch(obs, samples, advantages, kept, advantages.numel() if kept is None else kept.numel())

    def _sgd(self, batch: _TrainBatch, kl_coeff: float) -> list[float]:
        """``num_sgd_iter`` shuffled passes of minibatch Adam steps; the means over every minibatch of the policy
        loss, value loss, KL, entropy, clip fraction and total loss (over every rank)."""
        if self.recurrent:
            return self._sgd_sequences(self._sequences(batch), kl_coeff)
        cfg, dp, flat = self.config, self.dp, self.flat
        minibatch = min(cfg.sgd_minibatch_size, batch.size)
        num_minibatches = batch.size // minibatch
        flat.check()

        def reduce(x: torch.Tensor) -> torch.Tensor:
            return dp.minibatch_mean(x, minibatch)

        kl_weight = torch.tensor(kl_coeff, device=self.device) if kl_coeff > 0.0 else None
        # Sums over minibatches, kept on the device so that no step waits for a host sync.
        # policy, value, kl, entropy, clip fraction, total loss
        totals = self._graphed.totals.zero_() if self._graphed is not None else torch.zeros(6, device=self.device)
        if self._graphed is not None:
            self._graphed.begin_update()
        self.policy.train()
        for _ in range(cfg.num_sgd_iter):
            order = torch.randperm(batch.size, generator=self.generator, device=self.device)
            if batch.kept is not None:
                order = batch.kept[order]
            for i in range(num_minibatches):
                idx = order[i * minibatch : (i + 1) * minibatch]
                adv = batch.advantages[idx]
                if cfg.advantage_norm == "minibatch":
                    adv = standardize(adv)
                if self._graphed is not None:  # the same step, replayed (one process: idx is the minibatch)
                    self._graphed(batch.obs, batch.samples, adv, idx, kl_weight)
                    continue
                idx, adv = dp.local_share(idx, adv)
                flat.zero_grad()
                if idx.numel():  # a rank may hold none of a minibatch; it then adds zero gradients
                    loss, stats = self._minibatch_loss(self.policy, self.distribution, cfg,
                                                       obs_map(lambda x, i=idx: x.index_select(0, i), batch.obs),
                                                       batch.samples.index_select(0, idx), adv, kl_weight, reduce)
                    loss.backward()
                    totals += stats
                self._step(flat)
        dp.sum_(totals)  # each rank summed its shares of the minibatch means: their sum is the global mean
        return (totals / (cfg.num_sgd_iter * num_minibatches)).tolist()

    def _sequences(self, batch: _TrainBatch) -> _SequenceBatch:
        """The rollout as chunks of ``sequence_length`` steps per env (:class:`_SequenceBatch`); the advantages as
        ``batch`` holds them (standardised over the batch's real transitions)."""
        buf, dp = self.rollout, self.dp
        steps, envs = buf.rewards.shape
        length = min(self.config.sequence_length, steps)
        chunks = -(-steps // length)

        def cut(x: torch.Tensor) -> torch.Tensor:  # [T, N, ...] -> [L, C·N, ...]
            return chunked(x, length)

        assert buf.episode_starts is not None
        return _SequenceBatch(
            obs=obs_map(cut, buf.obs),
            samples=cut(batch.samples.reshape(steps, envs, -1)),
            advantages=cut(batch.advantages.reshape(steps, -1)),  # (global)
            starts=cut(buf.episode_starts),
            mask=cut(buf.valid),  # (padding: False)
            state=tuple(s[::length].reshape(chunks * envs, *s.shape[2:]) for s in buf.states),
            counted=cut(dp.gather_envs(buf.valid, dim=1)),
        )

    def _sgd_sequences(self, batch: _SequenceBatch, kl_coeff: float) -> list[float]:
        """:meth:`_sgd` for a recurrent policy: each pass shuffles the sequences and steps Adam on minibatches of
        ``max(1, sgd_minibatch_size // sequence_length)`` of them (``sgd_minibatch_size`` still counts steps), each
        run from its stored state (truncated BPTT). Data-parallel, every rank draws the same permutation of the global
        sequences and runs those of its envs (``dp.local_sequences``), the losses divided by the minibatch's global
        step count; the gradients are summed over ranks, as in :meth:`_sgd`."""
        cfg, flat, dp = self.config, self.flat, self.dp
        length, sequences = batch.counted.shape  # (global)
        per = min(sequences, max(1, cfg.sgd_minibatch_size // length))
        num_minibatches = sequences // per
        flat.check()
        kl_weight = torch.tensor(kl_coeff, device=self.device) if kl_coeff > 0.0 else None
        totals = torch.zeros(6, device=self.device)
        self.policy.train()
        for _ in range(cfg.num_sgd_iter):
            order = torch.randperm(sequences, generator=self.generator, device=self.device)
            for i in range(num_minibatches):
                idx = order[i * per : (i + 1) * per]
                counted, adv = batch.counted[:, idx], batch.advantages[:, idx]
                if cfg.advantage_norm == "minibatch":  # over the steps that count
                    adv = torch.where(counted, adv, 0.0).masked_scatter(counted, standardize(adv[counted]))
                local, mine = dp.local_sequences(idx)
                if mine is not None:
                    adv = adv[:, mine]
                flat.zero_grad()
                if local.numel():  # a rank may hold none of a minibatch; it then adds zero gradients
                    part = Sequences(obs_map(lambda x, i=local: x[:, i], batch.obs),
                                     tuple(s[local] for s in batch.state), batch.starts[:, local], batch.mask[:, local])
                    loss, stats = sequence_minibatch_loss(
                        self.policy, self.distribution, cfg, part,
                        batch.samples[:, local].reshape(length * local.numel(), -1), adv.reshape(-1), kl_weight,
                        counted.sum())
                    loss.backward()
                    totals += stats
                self._step(flat)
        dp.sum_(totals)  # each rank summed its shares of the minibatch means
        return (totals / (cfg.num_sgd_iter * num_minibatches)).tolist()

    def _step(self, flat: Any) -> None:
        """One optimiser step from the minibatch's gradients: summed over ranks, clipped, applied (both SGD loops)."""
        self.dp.all_reduce_grad_(flat.grad)
        if self.config.grad_clip is not None:
            flat.clip_grad_norm_(self.config.grad_clip)
        self.optimizer.step()

    def _minibatch_mean(self, x: torch.Tensor) -> torch.Tensor:
        """The minibatch mean (``Collectives.minibatch_mean``) at the configured minibatch size: the graphed step's
        ``reduce`` (its minibatches are full ones of one process)."""
        return self.dp.minibatch_mean(x, x.shape[0])

    def _lr_value(self, lr: float) -> float | torch.Tensor:
        """The optimizer's lr as it holds it: a device tensor when a graph reads it (``cuda_graph``), else a float."""
        return torch.tensor(float(lr), device=self.device) if self.config.cuda_graph else lr

    def _update_stats(self, batch: _TrainBatch, means: list[float], kl_coeff: float, lr: float) -> dict[str, float]:
        """The update's statistics over the global batch (the values, returns and σ gathered from every rank)."""
        buf, dp, kept = self.rollout, self.dp, batch.kept
        values = dp.gather_envs(buf.values, dim=1).reshape(-1)
        returns = dp.gather_envs(buf.returns, dim=1).reshape(-1)
        if kept is not None:
            values, returns = values[kept], returns[kept]
        stats = {
            "policy_loss": means[0],
            "value_loss": means[1],
            "approx_kl": means[2],
            "entropy": means[3],
            "clip_fraction": means[4],
            "total_loss": means[5],
            "kl_coeff": kl_coeff,
            "lr": lr,
            "explained_variance": explained_variance(values, returns),
            "value_mean": values.mean().item(),
        }
        if isinstance(self.distribution, DiagGaussian):  # σ is the Gaussian's own figure (the others': entropy)
            stds = dp.gather_envs(buf.log_stds, dim=1).exp()
            if kept is not None:
                stds = stds.reshape(-1, stds.shape[-1])[kept]
            if isinstance(self.distribution, MaskedDiagGaussian):  # over the entries that act
                mask = dp.gather_envs(buf.params[2], dim=1)
                mask = mask.reshape(-1, mask.shape[-1])[kept] if kept is not None else mask
                stats["action_std"] = ((stds * mask).sum() / mask.sum().clamp_min(1.0)).item()
            else:
                stats["action_std"] = stds.mean().item()
            for name, dims in (self.policy.action_groups if isinstance(self.policy, GroupedActions) else {}).items():
                stats[f"action_std_{name}"] = stds[..., dims].mean().item()
        return stats


__all__ = ["MinibatchUpdate", "own_code"]
