"""Running statistics for PPO's optional normalisations (``PPOConfig.obs_norm``, ``PPOConfig.reward_norm``).

``RunningMeanStd`` is the parallel mean/variance update of Chan et al. that Gymnasium's ``NormalizeObservation`` /
``NormalizeReward`` and Stable-Baselines3's ``VecNormalize`` use (float64, starting count 1e-4), kept as torch tensors
on the PPO device so that its state is three tensors in a checkpoint (``weights_only``-loadable).
"""

from __future__ import annotations

import torch


class RunningMeanStd:
    """Mean and (population) variance of every sample seen so far, per element of ``shape``.

    ``update(batch [B, *shape])`` folds in B samples; ``mean``/``var`` are float64 tensors of ``shape``.
    """

    def __init__(self, shape: tuple[int, ...], device: torch.device | str = "cpu", epsilon: float = 1e-4) -> None:
        self.mean = torch.zeros(shape, dtype=torch.float64, device=device)
        self.var = torch.ones(shape, dtype=torch.float64, device=device)
        self.count = float(epsilon)  # a python float: the update's scalar arithmetic stays off the tensor path

    def update(self, batch: torch.Tensor) -> None:
        # var <- (var·count + batch_var·n + delta²·count·n/total) / total, in place: with one env this runs at every
        # step for the observations and again for the returns, where each tensor op costs more than its arithmetic
        n = batch.shape[0]
        total = self.count + n
        if n == 1:  # a single sample has no spread of its own (the subtraction promotes it to float64)
            delta = batch[0] - self.mean
        else:
            batch_var, batch_mean = torch.var_mean(batch.to(self.mean.dtype), 0, correction=0)
            delta = batch_mean - self.mean
        self.var.mul_(self.count / total)
        if n > 1:
            self.var.add_(batch_var, alpha=n / total)
        self.var.addcmul_(delta, delta, value=self.count * n / (total * total))
        self.mean.add_(delta, alpha=n / total)
        self.count = total

    def update_steps(self, batches: torch.Tensor) -> torch.Tensor:
        """Fold in S batches one after the other (``batches [S, B, *shape]``, as S calls of ``update``) and return the
        variance after each, ``[S, *shape]``: what a rollout's reward scaling reads at each of its S steps.

        Chan's update is exact pooling, so the state after s batches is the pooled moments of the prior and those
        samples — prefix sums, not S small updates. Sums are taken about the prior mean (better conditioned).
        """
        x = batches.to(self.mean.dtype) - self.mean
        n = x.shape[1]
        sums, squares = x.sum(1).cumsum(0), x.square().sum(1).cumsum(0)
        counts = self.count + n * torch.arange(1, x.shape[0] + 1, dtype=x.dtype, device=x.device)
        counts = counts.reshape(-1, *([1] * (x.dim() - 2)))
        shift = sums / counts  # pooled mean − prior mean
        var = ((self.var * self.count + squares) / counts - shift.square()).clamp_min(0.0)
        self.mean = self.mean + shift[-1]
        self.var = var[-1].clone()
        self.count = self.count + n * x.shape[0]
        return var

    def normalize(self, x: torch.Tensor, clip: float, epsilon: float = 1e-8) -> torch.Tensor:
        """``clip((x − mean) / sqrt(var + ε), ±clip)`` as float32."""
        return self.normalize_with(x, self.mean, self.var, clip, epsilon)

    @staticmethod
    def normalize_with(x: torch.Tensor, mean: torch.Tensor, var: torch.Tensor, clip: float,
                       epsilon: float = 1e-8) -> torch.Tensor:
        """:meth:`normalize` with given statistics (what an exported policy folds in)."""
        out = (x - mean) / torch.sqrt(var + epsilon)  # float64: the subtraction promotes x
        return out.clamp(-clip, clip).to(torch.float32)

    def state_dict(self) -> dict[str, torch.Tensor]:
        count = torch.tensor(self.count, dtype=torch.float64)
        return {"mean": self.mean.clone(), "var": self.var.clone(), "count": count}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        device = self.mean.device
        self.mean, self.var = (state[k].to(device, torch.float64).clone() for k in ("mean", "var"))
        self.count = float(state["count"])
