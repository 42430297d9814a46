"""Patch embedding and token positions for the ViT encoder and the state tokens."""

from __future__ import annotations

import math

import torch
from torch import nn


class PatchEmbed(nn.Module):
    """Non-overlapping p x p patches -> tokens [B, N, C] with (row, col) positions [B, N, 2] (row-major)."""

    def __init__(self, in_channels: int, dim: int, patch_size: int = 16) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_channels, dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, _, H, W = x.shape
        p = self.patch_size
        if H % p or W % p:
            raise ValueError(f"image size {H}x{W} must be a multiple of the patch size {p}")
        tokens = self.proj(x).flatten(2).transpose(1, 2)
        pos = patch_positions(H // p, W // p, x.device).expand(B, -1, -1)
        return tokens, pos


def patch_positions(rows: int, cols: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """Integer (row, col) positions [1, rows*cols, 2] in row-major order."""
    r, c = torch.meshgrid(torch.arange(rows, device=device), torch.arange(cols, device=device), indexing="ij")
    return torch.stack((r.flatten(), c.flatten()), dim=-1)[None]


def state_positions(state_size: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """Positions [1, S, 2] of the state tokens on a grid of even width floor(sqrt(S)) (+1 when odd), as CUT3R."""
    width = math.isqrt(state_size)
    width += width % 2
    idx = torch.arange(state_size, device=device)
    return torch.stack((idx // width, idx % width), dim=-1)[None]
