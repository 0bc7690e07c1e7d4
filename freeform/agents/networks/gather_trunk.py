"""The voxel trunk's two convolutions as gathers and dense products: the deterministic GPU form (``trunk="gather"``).

Why: on a GPU cuDNN runs the paper's two one-output-channel 3-D convolutions in generic kernels (2.37 ms of a 2.40
ms minibatch step on an H200, ``docs/physics.md``, "The GPU"); the CPU's sparse trunk (``fast_trunk``) as CSR
products is 3× faster there, but cuSPARSE's products sum in a varying order, so runs do not repeat bit for bit.
This form is both: every shape fixed by the grid, nothing read on the host (a CUDA graph captures it), every sum a
gather followed by a reduction or a matrix product, in a fixed order on every device (1.64 ms a step):

* a one-output-channel convolution reads, for output o and kernel tap t, one input voxel ``window[o, t]`` (or the
  padding): ``cols = x[:, window]``, ``y = cols · w + b``; its input gradient is the transposed gather,
  ``∂L/∂x[j] = Σ_{(o, t) reading j} w[t] ∂L/∂y[o]``, over a table listing each input's readers (``fan`` ≤ 27);
* the first layer's input is one-hot, so ``cols · w`` is a lookup: ``y[o] = b + Σ_t W[material at window[o, t], t]``
  (the padding reads a zero row), and ``∂L/∂W[c, t] = Σ_{n, j} 1[g_nj = c] · ∂L/∂y[n, reader of j through t]``, one
  gather and one ``[k, N·ρ³] × [N·ρ³, 27]`` product.

Activations are sample-major (``[N, voxels]``) throughout. Tests pin both layers to ``nn.Conv3d`` (outputs and
gradients) on the CPU; the GPU check measures them against cuDNN (``benchmarks.bench_update``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from freeform.agents.networks.fast_trunk import conv_matrix, neighbour_table


@dataclass(frozen=True)
class ConvWindows:
    """The gather tables of Conv3d(1 → 1, kernel³, stride, padding) on a ``size³`` grid (C-order voxel indices).

    ``window [outputs, taps]``: the input voxel output o reads through tap t, or ``inputs`` (an appended zero) where
    it reads the padding. ``readers [inputs, fan]``: the flat ``o·taps + t`` of every (output, tap) reading input j,
    padded with ``outputs·taps`` (an appended zero)."""

    inputs: int
    outputs: int
    taps: int
    window: torch.Tensor
    readers: torch.Tensor


@functools.lru_cache(maxsize=32)
def conv_windows(size: int, kernel: int, stride: int, padding: int, device: torch.device) -> ConvWindows:
    """The tables of ``ConvWindows``, from ``fast_trunk.conv_matrix``'s entries (built once per geometry)."""
    s = conv_matrix(1, size, kernel, stride, padding, torch.device("cpu"))
    rows = torch.repeat_interleave(torch.arange(s.outputs), s.crow.diff())
    window = torch.full((s.outputs, s.taps), s.inputs, dtype=torch.int64)
    window[rows, s.tap] = s.col
    counts = s.t_crow.diff()
    fan = int(counts.max())
    slot = torch.arange(fan)
    pos = (s.t_crow[:-1, None] + slot[None, :]).clamp(max=len(s.t_col) - 1)
    readers = torch.where(slot[None, :] < counts[:, None], s.t_col[pos] * s.taps + s.t_tap[pos], s.outputs * s.taps)
    return ConvWindows(s.inputs, s.outputs, s.taps, window.to(device), readers.to(device))


@functools.lru_cache(maxsize=32)
def fed_through(size: int, device: torch.device) -> torch.Tensor:
    """For Conv3d(3³, stride 1, pad 1) on a ``size³`` grid, ``[size³, 27]``: the output that input voxel j feeds
    through tap t (``fast_trunk.neighbour_table``), or ``size³`` (an appended zero) off the grid."""
    table, _ = neighbour_table(size, device)
    return torch.where(table >= 0, table, size**3)


def _pad(x: torch.Tensor, value: float | int = 0) -> torch.Tensor:
    """``x [N, m]`` → ``[N, m + 1]``: one more column holding ``value`` (what a table's out-of-range index reads)."""
    return torch.cat([x, x.new_full((x.shape[0], 1), value)], dim=1)


class WindowConv(torch.autograd.Function):
    """``y [N, outputs] = x[:, window] · kernel + bias`` for ``x [N, inputs]``, ``kernel [taps]``, ``bias [1]``."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, kernel: torch.Tensor, bias: torch.Tensor, w: ConvWindows) -> torch.Tensor:  # type: ignore[override]
        n = x.shape[0]
        cols = _pad(x).index_select(1, w.window.view(-1)).view(n * w.outputs, w.taps)
        ctx.save_for_backward(cols, kernel)
        ctx.windows = w
        return torch.addmv(bias.expand(n * w.outputs), cols, kernel).view(n, w.outputs)

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        cols, kernel = ctx.saved_tensors
        w: ConvWindows = ctx.windows
        n = grad_y.shape[0]
        grad_y = grad_y.contiguous()
        grad_x = grad_kernel = grad_bias = None
        if ctx.needs_input_grad[0]:
            per_tap = (grad_y.unsqueeze(2) * kernel).view(n, w.outputs * w.taps)
            grad_x = _pad(per_tap).index_select(1, w.readers.view(-1)).view(n, w.inputs, -1).sum(2)
        if ctx.needs_input_grad[1]:
            grad_kernel = cols.t().mv(grad_y.view(-1))
        if ctx.needs_input_grad[2]:
            grad_bias = grad_y.sum().view(1)
        return grad_x, grad_kernel, grad_bias, None


class OneHotWindowConv(torch.autograd.Function):
    """Conv3d(k → 1, 3³, stride 1) of the one-hot of ``grids [N, inputs]`` (uint8 materials < k) as a table lookup:
    ``y [N, outputs] = bias + Σ_t kernel[grids[:, window[:, t]], t]`` for ``kernel [k, taps]``, ``bias [1]``;
    ``fed [inputs, taps]`` (``fed_through``) routes ∂L/∂y back to the input voxels for the weight gradient."""

    @staticmethod
    def forward(ctx, grids: torch.Tensor, kernel: torch.Tensor, bias: torch.Tensor, w: ConvWindows,  # type: ignore[override]
                fed: torch.Tensor) -> torch.Tensor:
        n, k = grids.shape[0], kernel.shape[0]
        # material k (a zero row of the table) where a tap reads the padding
        codes = _pad(grids, k).index_select(1, w.window.view(-1)).view(n, w.outputs, w.taps)
        taps = torch.arange(w.taps, device=grids.device, dtype=torch.int32)
        flat = (codes.to(torch.int32) * w.taps + taps).view(-1)
        table = torch.cat([kernel.reshape(-1), kernel.new_zeros(w.taps)])
        ctx.save_for_backward(grids, fed)
        ctx.windows, ctx.materials = w, k
        return table.index_select(0, flat).view(n, w.outputs, w.taps).sum(2) + bias

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        grids, fed_by = ctx.saved_tensors
        w: ConvWindows = ctx.windows
        n, k = grids.shape[0], ctx.materials
        grad_kernel = grad_bias = None
        if ctx.needs_input_grad[1]:
            # what each input voxel's material receives through each tap: ∂L/∂y of the output it feeds there
            fed = _pad(grad_y.contiguous()).index_select(1, fed_by.view(-1)).view(n * w.inputs, w.taps)
            materials = torch.arange(k, device=grids.device, dtype=grids.dtype)
            onehot = (grids.reshape(-1, 1) == materials).to(grad_y.dtype)  # [N·inputs, k]
            grad_kernel = onehot.t() @ fed
        if ctx.needs_input_grad[2]:
            grad_bias = grad_y.sum().view(1)
        return None, grad_kernel, grad_bias, None, None


def onehot_conv3d_gather(grids: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Conv3d(k→1, 3³, stride 1, pad 1) of the one-hot of uint8 ``grids [N, ρ, ρ, ρ]`` → float ``[N, ρ³]``;
    ``weight [1, k, 3, 3, 3]``, ``bias [1]``."""
    n, rho = grids.shape[0], grids.shape[1]
    windows = conv_windows(rho, 3, 1, 1, grids.device)
    return OneHotWindowConv.apply(grids.reshape(n, rho**3), weight.reshape(weight.shape[1], 27), bias, windows,
                                  fed_through(rho, grids.device))


def strided_conv3d_gather(x: torch.Tensor, resolution: int, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Conv3d(1→1, 5³, stride 2, pad 2) on sample-major ``x [N, ρ³]`` → ``[N, ⌈ρ/2⌉³]``; ``weight [1, 1, 5, 5, 5]``."""
    windows = conv_windows(resolution, 5, 2, 2, x.device)
    return WindowConv.apply(x.contiguous(), weight.reshape(-1), bias, windows)
