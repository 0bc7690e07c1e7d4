"""A network's trainable parameters as views of one flat tensor, and their gradients as views of another.

Why: a small network's update step (the 64-64 MLPs of a Gymnasium task: 13 tensors, ≈ 10k numbers) costs what its
Python-level operations cost, and zeroing the gradients, their global norm for clipping and Adam each cost one
operation per tensor. Over one flat tensor each is a single operation. Backward accumulates into the gradient views
in place (they are zeroed, never set to None), and the module keeps its parameters, so nothing else changes: its
state dict, loading into it, and the numbers — Adam is elementwise, so the flat tensor gets the per-tensor update
bit for bit.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
import torch.nn as nn


class FlatParameters:
    """``params`` (the trainable ones; all of one dtype and device) re-seated as views of ``value [P]``, their
    gradients as views of ``grad [P]`` (``value.grad``). Optimise ``[value]``; after ``zero_grad()`` and a backward
    pass ``grad`` holds every parameter's gradient."""

    def __init__(self, params: Iterable[nn.Parameter]) -> None:
        every = list(params)
        self._trainable = [p.requires_grad for p in every]
        self.params = [p for p in every if p.requires_grad]
        if not self.params:
            raise ValueError("the policy has no trainable parameters")
        kinds = {(p.dtype, p.device) for p in self.params}
        if len(kinds) > 1:
            raise ValueError(f"the policy's parameters must share one dtype and device, got {sorted(map(str, kinds))}")
        with torch.no_grad():
            self.value = nn.Parameter(torch.cat([p.detach().reshape(-1) for p in self.params]))
        self.grad = torch.zeros_like(self.value)
        self.value.grad = self.grad
        offset = 0
        for p in self.params:
            n = p.numel()
            p.data = self.value.data[offset : offset + n].view_as(p)
            p.grad = self.grad[offset : offset + n].view_as(p)
            offset += n

    def zero_grad(self) -> None:
        self.grad.zero_()

    def clip_grad_norm_(self, max_norm: float) -> torch.Tensor:
        """``torch.nn.utils.clip_grad_norm_`` on the flat gradient: scale it by min(1, max_norm / (‖g‖₂ + 1e-6));
        returns ‖g‖₂ before scaling."""
        total = torch.linalg.vector_norm(self.grad)
        self.grad.mul_((max_norm / (total + 1e-6)).clamp(max=1.0))
        return total

    def check(self) -> None:
        """Re-seat gradients that were replaced (``zero_grad()`` sets them to None) and raise ``RuntimeError`` if a
        parameter was (``policy.to(...)`` after PPO was built): the flat tensor would no longer be what it trains."""
        offset = 0
        for p in self.params:
            n = p.numel()
            if p.data_ptr() != self.value[offset:].data_ptr():
                raise RuntimeError("a policy parameter was replaced after PPO was built (moved or cast?): build PPO "
                                   "after moving the policy")
            if p.grad is None or p.grad.data_ptr() != self.grad[offset:].data_ptr():
                p.grad = self.grad[offset : offset + n].view_as(p)
            offset += n

    def optimizer_state(self, state: dict[str, Any]) -> dict[str, Any]:
        """An optimizer state dict over ``[value]``: ``state`` itself, or one saved over the module's parameters one
        by one (checkpoints written before the flat vector, whose Adam held every parameter in order, frozen ones
        without moments), with the trainable parameters' moments concatenated in order."""
        groups = state["param_groups"]
        ids = groups[0]["params"] if len(groups) == 1 else None
        if ids is not None and len(ids) <= 1:
            return state
        if ids is None or len(ids) != len(self._trainable):
            raise ValueError(f"the optimizer state holds {[len(g['params']) for g in groups]} parameter tensors; "
                             f"this policy has {len(self._trainable)} (one group expected)")
        per_param = [state["state"].get(i, {}) for i, trainable in zip(ids, self._trainable, strict=True) if trainable]
        flat: dict[Any, Any] = {}
        if any(per_param):
            if not all(per_param):
                raise ValueError("the optimizer state has moments for some trainable parameters but not others")
            step = per_param[0]["step"]
            flat[0] = {"step": step.clone() if isinstance(step, torch.Tensor) else step}
            for key in per_param[0]:
                if key != "step":
                    flat[0][key] = torch.cat([s[key].reshape(-1) for s in per_param])
        return {"state": flat, "param_groups": [{**groups[0], "params": [0]}]}
