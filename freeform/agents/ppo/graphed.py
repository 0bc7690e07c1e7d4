"""One minibatch's whole Adam step — zero the gradient, the loss, backward, clipping, Adam — as a CUDA graph.

Why: on a GPU a minibatch of 128 samples through the paper's network costs its ≈ 300 kernel launches, not their
arithmetic (5.0–5.4 ms on an H100, ``gpu-measured.md``). Captured once and replayed, the step is one launch; only
the minibatch's rows are copied into the graph's fixed input buffers before each replay.

The step is the eager one (``PPO._sgd``), the same functions in the same order. What a graph needs, and how it is
met: fixed shapes (one process: every minibatch has ``sgd_minibatch_size`` samples; data parallel is refused, a
rank's share varies), fixed addresses (the inputs are copied into buffers the graph reads; the flat parameter and
gradient tensors are fixed already), and no host synchronisation inside the step: Adam is built ``capturable``
(its step count and learning rate live on the device). The first ``WARMUP`` steps of every update run eagerly, on
a side stream, through the same buffers — at the first update they initialise Adam's moments and the libraries'
workspaces, which a capture may not allocate — then the first update captures its next step, and every later step
is a replay. Loading a state drops the graph (the optimizer's tensors are new); the next update captures again.
Why every update and not only the first: an eager step and a replay need not agree to the bit (measured on an H200:
they do not), so a resumed run, which must warm up again, would drift from a straight one; with the same eager
steps in every update the two compute the same sequence, and resume stays bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.ppo.config import PPOConfig
from freeform.agents.ppo.flat_params import FlatParameters
from freeform.agents.ppo.losses import minibatch_loss
from freeform.agents.ppo.rollout import Observation, obs_map
from freeform.distributions import ActionDistribution

WARMUP = 3
"""Eager steps before the capture (PyTorch's recipe: autograd's and cuBLAS's first calls allocate)."""


class GraphedMinibatchStep:
    """``step(obs, samples, advantages, idx, kl_weight)``: the Adam step on the rows ``idx [M]`` of ``obs [B, ...]``
    and ``samples [B, A + P + 3]`` with ``advantages [M]``; the step's statistics are added to ``totals [6]``.
    ``advantages`` as the eager step takes them (standardised per minibatch already where configured); ``kl_weight`` β
    as a 0-d device tensor or None (no KL penalty: another graph)."""

    def __init__(self, policy: nn.Module, dist: ActionDistribution, cfg: PPOConfig, flat: FlatParameters,
                 optimizer: torch.optim.Optimizer, reduce: Callable[[torch.Tensor], torch.Tensor], device: torch.device):
        self.policy, self.dist, self.cfg, self.flat, self.optimizer, self.reduce = policy, dist, cfg, flat, optimizer, reduce
        self.device = device
        self.totals = torch.zeros(6, device=device)
        self._inputs: dict[str, Any] | None = None
        self._graphs: dict[bool, torch.cuda.CUDAGraph] = {}
        self._eager_left = WARMUP
        self._stream = torch.cuda.Stream(device)

    def begin_update(self) -> None:
        """Called at the start of every update: its first ``WARMUP`` steps run eagerly."""
        self._eager_left = WARMUP

    def reset(self) -> None:
        """Forget the graphs (after the optimizer's or the policy's tensors were replaced: ``load_state_dict``)."""
        self._graphs.clear()

    def _buffers(self, obs: Observation, samples: torch.Tensor, size: int) -> dict[str, Any]:
        if self._inputs is None or self._inputs["samples"].shape != (size, samples.shape[1]):
            self._graphs.clear()
            self._inputs = {
                "obs": obs_map(lambda x: torch.empty((size, *x.shape[1:]), dtype=x.dtype, device=x.device), obs),
                "samples": torch.empty((size, samples.shape[1]), dtype=samples.dtype, device=samples.device),
                "advantages": torch.empty(size, device=self.device),
                "kl_weight": torch.zeros((), device=self.device),
            }
        return self._inputs

    def _body(self, with_kl: bool) -> None:
        """The eager step of ``PPO._sgd`` on the input buffers (what the graph records)."""
        cfg, inputs = self.cfg, self._inputs
        assert inputs is not None
        self.flat.zero_grad()
        loss, stats = minibatch_loss(self.policy, self.dist, cfg, inputs["obs"], inputs["samples"], inputs["advantages"],
                                     inputs["kl_weight"] if with_kl else None, self.reduce)
        loss.backward()
        self.totals.add_(stats)
        if cfg.grad_clip is not None:
            self.flat.clip_grad_norm_(cfg.grad_clip)
        self.optimizer.step()

    def __call__(self, obs: Observation, samples: torch.Tensor, advantages: torch.Tensor, idx: torch.Tensor,
                 kl_weight: torch.Tensor | None) -> None:
        inputs = self._buffers(obs, samples, idx.numel())
        if isinstance(obs, dict):
            for key, src in obs.items():
                torch.index_select(src, 0, idx, out=inputs["obs"][key])
        else:
            torch.index_select(obs, 0, idx, out=inputs["obs"])
        torch.index_select(samples, 0, idx, out=inputs["samples"])
        inputs["advantages"].copy_(advantages)
        with_kl = kl_weight is not None
        if with_kl:
            inputs["kl_weight"].copy_(kl_weight)
        graph = self._graphs.get(with_kl) if self._eager_left == 0 else None
        if graph is not None:
            graph.replay()
            return
        current = torch.cuda.current_stream(self.device)
        self._stream.wait_stream(current)
        with torch.cuda.stream(self._stream):
            if self._eager_left > 0:
                self._body(with_kl)
                self._eager_left -= 1
            else:
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph, stream=self._stream):
                    self._body(with_kl)
                self._graphs[with_kl] = graph
        current.wait_stream(self._stream)
        if graph is not None:  # the capture recorded the step without running it
            graph.replay()
