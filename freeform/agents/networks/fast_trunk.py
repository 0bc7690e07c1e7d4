"""The voxel trunk's two convolutions as sparse-matrix products — the same maps as ``nn.Conv3d``, much faster.

Why: on a CPU, PyTorch's Conv3d spends most of a training step of the paper's network in two tiny layers (one
output channel each): the input-gradient of the strided 5³ convolution and the weight-gradient of the 3³ one. A
single-output-channel convolution over a fixed grid is a fixed sparse matrix M (one row per output voxel, one
stored entry per (input voxel, kernel tap) pair in its window) whose stored values are kernel weights:

    y = M(w) x,   ∂L/∂x = M(w)ᵀ ∂L/∂y,   ∂L/∂w[tap] = Σ_{entries e of that tap} (∂L/∂y · xᵀ)[e]

— a CSR × dense product (SpMM) forward, another one backward, and a *sampled* dense product (SDDMM) reduced per
tap for the weight gradient. The batch rides along as the dense operand's columns, so the work is a few 16M-MAC
sparse products per minibatch instead of im2col copies or transposed convolutions. Activations travel
voxel-major (``[voxels, N]``) between the two layers; the public functions take and return the usual
``[N, 1, ρ, ρ, ρ]`` shapes as free views of that layout.

The first layer's input is one-hot: with ``inside`` = 1 on the grid (0 in the zero padding), channel 0 equals
``inside − Σ_{c≥1} 1[g = c]``, so conv(onehot, w) = Σ_{c≥1} conv(1[g = c], w_c − w_0) + conv(inside, w_0). The last
term does not depend on the grid (a [ρ³, 27] validity mask times w_0), so the layer needs only the k − 1 indicator
channels and never builds the one-hot tensor. Design grids are sparse (≤ ~4 % of voxels filled), so when few
indicators are set the layer scatters each occupied voxel's 27 weights into its neighbours (``index_add_``) and its
weight gradient gathers ∂L/∂y there; denser batches use the CSR product.

On the CPU every reduction has a fixed order (``index_add_`` is sequential there; the CSR weight gradient sums a
padded per-tap table), so results are deterministic for a given thread count. (On CUDA ``index_add_`` uses atomics;
``VoxelActorCritic(trunk="auto")`` runs nn.Conv3d there.)
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ConvMatrix:
    """The sparsity structure of a 1-output-channel Conv3d as an ``[outputs, inputs]`` CSR matrix, and its transpose.

    ``crow/col/tap``: CSR row pointers, column indices and the kernel-tap index of every stored entry (entries of a
    row sorted by column); ``t_crow/t_col/t_tap``: the same for Mᵀ. ``tap_table [taps, max_count]`` lists the entries
    of each tap, padded with ``nnz`` (which indexes an appended zero) so that a per-tap sum is one gather + sum.
    """

    outputs: int
    inputs: int
    taps: int
    crow: torch.Tensor
    col: torch.Tensor
    tap: torch.Tensor
    t_crow: torch.Tensor
    t_col: torch.Tensor
    t_tap: torch.Tensor
    tap_table: torch.Tensor

    def matrix(self, kernel: torch.Tensor) -> torch.Tensor:
        """M with values ``kernel[tap]``: sparse CSR ``[outputs, inputs]``; ``kernel`` is ``[taps]``."""
        return _csr(self.crow, self.col, kernel.index_select(0, self.tap), (self.outputs, self.inputs))

    def transpose(self, kernel: torch.Tensor) -> torch.Tensor:
        """Mᵀ with values ``kernel[tap]``: sparse CSR ``[inputs, outputs]``."""
        return _csr(self.t_crow, self.t_col, kernel.index_select(0, self.t_tap), (self.inputs, self.outputs))


def _csr(crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the ops used here are long stable
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, values, size, check_invariants=False)


def _crow(rows: torch.Tensor, n_rows: int) -> torch.Tensor:
    counts = torch.bincount(rows, minlength=n_rows)
    return torch.cat([counts.new_zeros(1), counts.cumsum(0)])


@functools.lru_cache(maxsize=32)
def conv_matrix(
    in_channels: int, size: int, kernel: int, stride: int, padding: int, device: torch.device
) -> ConvMatrix:
    """Structure of Conv3d(in_channels → 1, kernel³, stride, padding) on a ``size³`` grid, zero padding.

    Input index j = c·size³ + (x·size + y)·size + z (C order, channel slowest); output index likewise over the
    output grid; tap index = (c·kernel + a)·kernel² + b·kernel + d, the flat index of ``weight[0, c, a, b, d]``.
    """
    out = (size + 2 * padding - kernel) // stride + 1
    ar_out, ar_k = torch.arange(out), torch.arange(kernel)
    # Per axis: input coordinate of (output coordinate, kernel offset), and whether it lies inside the grid.
    coord = stride * ar_out[:, None] + ar_k[None, :] - padding  # [out, kernel]
    valid = (coord >= 0) & (coord < size)
    # Every (output voxel, channel, tap) combination, broadcast to [out, out, out, C, k, k, k].
    shape = (out, out, out, in_channels, kernel, kernel, kernel)
    ox = ar_out.view(-1, 1, 1, 1, 1, 1, 1)
    oy = ar_out.view(1, -1, 1, 1, 1, 1, 1)
    oz = ar_out.view(1, 1, -1, 1, 1, 1, 1)
    ch = torch.arange(in_channels).view(1, 1, 1, -1, 1, 1, 1)
    ka = ar_k.view(1, 1, 1, 1, -1, 1, 1)
    kb = ar_k.view(1, 1, 1, 1, 1, -1, 1)
    kd = ar_k.view(1, 1, 1, 1, 1, 1, -1)
    ix, iy, iz = coord[ox, ka], coord[oy, kb], coord[oz, kd]
    inside = (valid[ox, ka] & valid[oy, kb] & valid[oz, kd]).expand(shape)
    row = ((ox * out + oy) * out + oz).expand(shape)[inside]
    col = (ch * size**3 + (ix * size + iy) * size + iz).expand(shape)[inside]
    tap = (((ch * kernel + ka) * kernel + kb) * kernel + kd).expand(shape)[inside]
    # CSR needs entries by row, then column; C-order enumeration gives rows ascending but columns unsorted.
    order = torch.argsort(row * (in_channels * size**3) + col)
    row, col, tap = row[order], col[order], tap[order]
    t_order = torch.argsort(col * out**3 + row)
    n_taps = in_channels * kernel**3
    # Per-tap entry lists, padded with the index nnz (an appended zero value) to the longest list.
    by_tap = torch.argsort(tap, stable=True)
    counts = torch.bincount(tap, minlength=n_taps)
    starts = torch.cat([counts.new_zeros(1), counts.cumsum(0)[:-1]])
    slot = torch.arange(int(counts.max()))
    pos = starts[:, None] + slot[None, :]
    table = torch.where(slot[None, :] < counts[:, None], by_tap[pos.clamp(max=len(tap) - 1)], len(tap))
    to = functools.partial(torch.Tensor.to, device=device)
    return ConvMatrix(
        outputs=out**3,
        inputs=in_channels * size**3,
        taps=n_taps,
        crow=to(_crow(row, out**3)),
        col=to(col),
        tap=to(tap),
        t_crow=to(_crow(col[t_order], in_channels * size**3)),
        t_col=to(row[t_order]),
        t_tap=to(tap[t_order]),
        tap_table=to(table),
    )


class SparseConv(torch.autograd.Function):
    """y = M(kernel) x + shift for voxel-major activations.

    ``x [inputs, N]``, ``kernel [taps]``, ``shift`` broadcastable to ``[outputs, N]`` (a bias, or a per-voxel
    column) → ``y [outputs, N]``.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, kernel: torch.Tensor, shift: torch.Tensor, structure: ConvMatrix) -> torch.Tensor:  # type: ignore[override]
        ctx.structure = structure
        ctx.shift_shape = shift.shape
        ctx.save_for_backward(x, kernel)
        # addmm starts from the shift instead of zero-filling the output and adding it afterwards.
        return torch.addmm(shift, structure.matrix(kernel), x)

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        x, kernel = ctx.saved_tensors
        s: ConvMatrix = ctx.structure
        grad_y = grad_y.contiguous()
        grad_x = grad_kernel = grad_shift = None
        if ctx.needs_input_grad[0]:
            grad_x = s.transpose(kernel) @ grad_y
        if ctx.needs_input_grad[1]:
            # (∂L/∂y · xᵀ) only at M's stored entries, then summed per kernel tap.
            pattern = _csr(s.crow, s.col, grad_y.new_zeros(len(s.col)), (s.outputs, s.inputs))
            entries = torch.sparse.sampled_addmm(pattern, grad_y, x.t(), beta=0.0).values()
            padded = torch.cat([entries, entries.new_zeros(1)])
            grad_kernel = padded.index_select(0, s.tap_table.view(-1)).view(s.tap_table.shape).sum(1)
        if ctx.needs_input_grad[2]:
            grad_shift = grad_y.sum(1, keepdim=True) if len(ctx.shift_shape) == 2 else grad_y.sum().reshape(ctx.shift_shape)
            if len(ctx.shift_shape) == 2 and ctx.shift_shape[0] == 1:
                grad_shift = grad_shift.sum(0, keepdim=True)
        return grad_x, grad_kernel, grad_shift, None


@functools.lru_cache(maxsize=32)
def neighbour_table(size: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """For Conv3d(3³, stride 1, pad 1) on a ``size³`` grid: ``table [size³, 27] int64``, the output voxel that input
    voxel j feeds through tap t (``weight[..., a, b, d]``, t = 9a + 3b + d), or −1 off the grid; and ``valid
    [size³, 27] float32``, 1 where output voxel i's tap t reads a voxel inside the grid (not the zero padding)."""
    ar = torch.arange(size)
    x, y, z = (c.reshape(-1, 1) for c in torch.meshgrid(ar, ar, ar, indexing="ij"))
    off = torch.arange(3)
    a, b, d = (o.reshape(1, -1) for o in torch.meshgrid(off, off, off, indexing="ij"))
    # y[i] = Σ_t w[t] x[i + t − 1] (per axis), so input j reaches output i = j − t + 1.
    ox, oy, oz = x - a + 1, y - b + 1, z - d + 1
    inside = (ox >= 0) & (ox < size) & (oy >= 0) & (oy < size) & (oz >= 0) & (oz < size)
    table = torch.where(inside, (ox * size + oy) * size + oz, -1)
    # The cube is symmetric: output i's tap t reads inside the grid iff the mirrored input voxel feeds it.
    ix, iy, iz = x + a - 1, y + b - 1, z + d - 1
    valid = (ix >= 0) & (ix < size) & (iy >= 0) & (iy < size) & (iz >= 0) & (iz < size)
    return table.to(device), valid.to(device=device, dtype=torch.float32)


@functools.lru_cache(maxsize=32)
def scatter_tables(size: int, n: int, materials: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Per input voxel j and tap t, for a voxel-major ``[size³, n]`` output: ``targets [size³, 27]`` = i·n (i the
    output voxel j feeds through t; 0 off the grid) and ``weights [size³, 27]`` = t, or t + (k−1)·27 off the grid —
    an index into the kernel followed by (k−1)·27 zeros, so misses add 0 without any compaction. int32 when the
    flat output fits (index ops move half the bytes)."""
    table, _ = neighbour_table(size, device)
    dtype = torch.int32 if size**3 * n < 2**31 else torch.int64
    hit = table >= 0
    targets = torch.where(hit, table * n, 0).to(dtype)
    weights = (torch.arange(27, device=device) + torch.where(hit, 0, (materials - 1) * 27)).to(dtype)
    return targets, weights


class OccupiedScatterConv(torch.autograd.Function):
    """The first layer's indicator part from the occupied voxels only: design grids are ≤ a few % full.

    ``targets, weight_index [nnz·27]``: for each occupied voxel and tap, the flat index into ``y [ρ³·N]`` it feeds
    and the index into ``[kernel.flatten(), zeros]`` of its weight (see ``scatter_tables``); ``kernel [k−1, 27]``
    (w_c − w_0); ``shift [ρ³, 1]`` → ``y [ρ³, N] = shift + the scattered weights``. The weight gradient gathers
    ∂L/∂y at the same places. Sums run in a fixed order on the CPU (``index_add_`` is sequential there).
    """

    @staticmethod
    def forward(ctx, targets, weight_index, kernel, shift, n: int):  # type: ignore[override]
        voxels = shift.shape[0]
        weights = torch.cat([kernel.reshape(-1), kernel.new_zeros(kernel.numel())])
        out = torch.empty((voxels, n), dtype=kernel.dtype, device=kernel.device).copy_(shift.expand(voxels, n))
        out.view(-1).index_add_(0, targets, weights.index_select(0, weight_index))
        ctx.save_for_backward(targets, weight_index)
        ctx.kernel_shape = kernel.shape
        return out

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor):  # type: ignore[override]
        targets, weight_index = ctx.saved_tensors
        grad_y = grad_y.contiguous()
        gathered = grad_y.view(-1).index_select(0, targets)
        n_weights = ctx.kernel_shape.numel()
        grad_kernel = gathered.new_zeros(2 * n_weights).index_add_(0, weight_index, gathered)[:n_weights]
        return None, None, grad_kernel.view(ctx.kernel_shape), grad_y.sum(1, keepdim=True), None


#: Scatter from the occupied voxels while they number at most this fraction of the (k − 1)·ρ³·N indicator entries
#: the CSR product would multiply. Measured (CPU, one thread, N = 128, k = 2 design states 2.2 % full): scatter
#: ≈ 1.7 ms index preparation + 1.3 forward + 1.3 backward vs CSR ≈ 0.7 indicator + 3.6 SpMM + 3.0 SDDMM. The
#: scatter's cost grows with the filled voxels, the product's with k − 1; they meet near 3.5 % per channel.
#: Both paths compute the same map (tests pin both to nn.Conv3d).
SCATTER_MAX_DENSITY = 0.035


def onehot_conv3d_voxel_major(grids: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor,
                              dense: bool = False) -> torch.Tensor:
    """Conv3d(k→1, 3³, stride 1, pad 1) of the one-hot of uint8 ``grids [N, ρ, ρ, ρ]`` → float ``[ρ³, N]``.

    ``weight [1, k, 3, 3, 3]``, ``bias [1]``; output row = the voxel's C-order index. Sparse grids (the design
    states) are scattered from their occupied voxels; dense ones go through the CSR product, and so does every grid
    with ``dense`` (no count read on the host: what a CUDA graph can capture).
    """
    n, rho = grids.shape[0], grids.shape[1]
    k = weight.shape[1]
    device = grids.device
    voxels = rho**3
    grid_t = grids.reshape(n, voxels).t().contiguous()  # voxel-major [ρ³, N] uint8
    w0 = weight[:, :1]
    relative = (weight[:, 1:] - w0).reshape(k - 1, 27)  # w_c − w_0, c ≥ 1
    # conv(inside, w_0) + bias: the same for every grid, a [ρ³, 1] column (taps that read the padding drop out).
    table, valid = neighbour_table(rho, device)
    base = (valid.to(weight.dtype) @ w0.reshape(27) + bias).unsqueeze(1)
    if not dense and int(torch.count_nonzero(grid_t)) <= SCATTER_MAX_DENSITY * (k - 1) * voxels * n:
        target_table, weight_table = scatter_tables(rho, n, k, device)
        flat = grid_t.view(-1).nonzero().squeeze(1)  # occupied entries of [ρ³, N], C order
        voxel = flat // n
        sample = (flat - voxel * n).to(target_table.dtype)
        targets = (target_table.index_select(0, voxel) + sample[:, None]).view(-1)
        weight_index = weight_table.index_select(0, voxel)
        if k > 2:  # material c ≥ 1 uses kernel row c − 1
            channel = grid_t.view(-1).index_select(0, flat).to(weight_table.dtype) - 1
            weight_index = weight_index + 27 * channel[:, None]
        return OccupiedScatterConv.apply(targets, weight_index.view(-1), relative, base, n)
    # Indicators of materials 1..k−1, voxel-major: [(k−1)·ρ³, N], written straight as floats.
    if k == 2:
        indicators = grid_t.to(weight.dtype)  # 0/1 already
    else:
        materials = torch.arange(1, k, device=device, dtype=grids.dtype).view(-1, 1, 1)
        indicators = torch.empty((k - 1, voxels, n), device=device, dtype=weight.dtype)
        torch.eq(grid_t.unsqueeze(0), materials, out=indicators)
        indicators = indicators.view((k - 1) * voxels, n)
    return SparseConv.apply(indicators, relative.reshape(-1), base, conv_matrix(k - 1, rho, 3, 1, 1, device))


def strided_conv3d_voxel_major(x: torch.Tensor, resolution: int, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Conv3d(1→1, 5³, stride 2, pad 2) on voxel-major ``x [ρ³, N]`` → ``[⌈ρ/2⌉³, N]``; ``weight [1, 1, 5, 5, 5]``."""
    structure = conv_matrix(1, resolution, 5, 2, 2, x.device)
    return SparseConv.apply(x.contiguous(), weight.reshape(-1), bias.view(1, 1), structure)


def onehot_conv3d(grids: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``onehot_conv3d_voxel_major`` in the usual layout: → ``[N, 1, ρ, ρ, ρ]`` (a view, no copy)."""
    n, rho = grids.shape[0], grids.shape[1]
    return onehot_conv3d_voxel_major(grids, weight, bias).t().reshape(n, 1, rho, rho, rho)


def strided_conv3d(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Conv3d(1→1, 5³, stride 2, pad 2): float ``[N, 1, ρ, ρ, ρ]`` → ``[N, 1, ⌈ρ/2⌉, ⌈ρ/2⌉, ⌈ρ/2⌉]``."""
    n, rho = x.shape[0], x.shape[2]
    y = strided_conv3d_voxel_major(x.reshape(n, rho**3).t(), rho, weight, bias)
    half = (rho - 1) // 2 + 1
    return y.t().reshape(n, 1, half, half, half)
