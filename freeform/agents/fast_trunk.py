"""Fast forms of the voxel trunk's two convolutions (placeholder: plain conv3d; optimised forms follow)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def onehot_conv3d(grids: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Conv3d(k→1, 3³, pad 1) of the one-hot of uint8 ``grids [N, ρ, ρ, ρ]`` → float ``[N, 1, ρ, ρ, ρ]``."""
    k = weight.shape[1]
    channels = torch.arange(k, device=grids.device, dtype=grids.dtype).view(1, -1, 1, 1, 1)
    x = (grids.unsqueeze(1) == channels).to(weight.dtype)
    return F.conv3d(x, weight, bias, padding=1)


def strided_conv3d(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Conv3d(1→1, 5³, stride 2, pad 2): float ``[N, 1, ρ, ρ, ρ]`` → ``[N, 1, ⌈ρ/2⌉, ⌈ρ/2⌉, ⌈ρ/2⌉]``."""
    return F.conv3d(x, weight, bias, stride=2, padding=2)
