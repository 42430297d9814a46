"""Transformer building blocks: 2D RoPE, attention (through SDPA), MLP, encoder/decoder blocks, adaLN blocks.

Sub-module names match CUT3R's so its state_dict loads without renaming.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

LN_EPS = 1e-6


def _rotate_half(x: torch.Tensor) -> torch.Tensor:
    first, second = x.chunk(2, dim=-1)
    return torch.cat((-second, first), dim=-1)


def apply_rope_2d(x: torch.Tensor, positions: torch.Tensor, base: float = 100.0) -> torch.Tensor:
    """Rotate queries or keys x [B, heads, N, d] by 2D token positions [B, N, 2] (row, col).

    The first d/2 channels rotate with the row, the last d/2 with the column (rotate-half pairing inside each half).
    cos/sin are computed from the signed positions, so the pose token at (-1, -1) is fine.
    """
    d = x.shape[-1]
    half = d // 2
    inv_freq = base ** (-torch.arange(0, half, 2, device=x.device, dtype=torch.float32) / half)
    out = []
    for axis, part in enumerate(x.split(half, dim=-1)):
        angles = positions[..., axis].to(torch.float32)[..., None] * inv_freq  # [B, N, half/2]
        angles = torch.cat((angles, angles), dim=-1)[:, None]  # [B, 1, N, half]
        cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
        out.append(part * cos + _rotate_half(part) * sin)
    return torch.cat(out, dim=-1)


class Mlp(nn.Module):
    """Linear -> exact GELU -> Linear."""

    def __init__(self, dim: int, hidden: int, out_dim: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, out_dim or dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class SelfAttention(nn.Module):
    """Multi-head self-attention with fused qkv and optional 2D RoPE."""

    def __init__(self, dim: int, heads: int, rope_base: float | None = 100.0) -> None:
        super().__init__()
        self.heads = heads
        self.rope_base = rope_base
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        B, N, C = x.shape
        q, k, v = self.qkv(x).reshape(B, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        if pos is not None and self.rope_base is not None:
            q, k = apply_rope_2d(q, pos, self.rope_base), apply_rope_2d(k, pos, self.rope_base)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(B, N, C))


class CrossAttention(nn.Module):
    """Multi-head cross-attention (separate q/k/v projections); RoPE on q with x's and on k with y's positions."""

    def __init__(self, dim: int, heads: int, rope_base: float | None = 100.0) -> None:
        super().__init__()
        self.heads = heads
        self.rope_base = rope_base
        self.projq = nn.Linear(dim, dim)
        self.projk = nn.Linear(dim, dim)
        self.projv = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)

    def _split(self, t: torch.Tensor) -> torch.Tensor:
        B, N, C = t.shape
        return t.reshape(B, N, self.heads, C // self.heads).transpose(1, 2)

    def forward(self, x: torch.Tensor, y: torch.Tensor, x_pos: torch.Tensor | None = None,
                y_pos: torch.Tensor | None = None) -> torch.Tensor:
        B, N, C = x.shape
        q, k, v = self._split(self.projq(x)), self._split(self.projk(y)), self._split(self.projv(y))
        if self.rope_base is not None and x_pos is not None and y_pos is not None:
            q, k = apply_rope_2d(q, x_pos, self.rope_base), apply_rope_2d(k, y_pos, self.rope_base)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(B, N, C))


class EncoderBlock(nn.Module):
    """Pre-norm ViT block: x + Attn(LN(x)), then x + MLP(LN(x))."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, rope_base: float | None = 100.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LN_EPS)
        self.attn = SelfAttention(dim, heads, rope_base)
        self.norm2 = nn.LayerNorm(dim, eps=LN_EPS)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), pos)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Pre-norm block of the stream x reading the stream y: self-attention, cross-attention to LN_y(y), MLP."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, rope_base: float | None = 100.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LN_EPS)
        self.attn = SelfAttention(dim, heads, rope_base)
        self.norm2 = nn.LayerNorm(dim, eps=LN_EPS)
        self.cross_attn = CrossAttention(dim, heads, rope_base)
        self.norm3 = nn.LayerNorm(dim, eps=LN_EPS)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.norm_y = nn.LayerNorm(dim, eps=LN_EPS)

    def forward(self, x: torch.Tensor, y: torch.Tensor, x_pos: torch.Tensor | None = None,
                y_pos: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), x_pos)
        x = x + self.cross_attn(self.norm2(x), self.norm_y(y), x_pos, y_pos)
        return x + self.mlp(self.norm3(x))


class ModulatedLayerNorm(nn.Module):
    """adaLN: LN(x) * (1 + scale) + shift with [shift, scale] = Linear(SiLU(c))."""

    def __init__(self, dim: int, cond_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim, eps=LN_EPS)
        self.mlp = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 2 * dim))

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        shift, scale = self.mlp(cond).unsqueeze(1).chunk(2, dim=-1)
        return self.norm(x) * (1 + scale) + shift


class ModulatedBlock(nn.Module):
    """ViT block whose two norms are modulated by a conditioning vector (the output pose token)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, rope_base: float | None = 100.0) -> None:
        super().__init__()
        self.norm1 = ModulatedLayerNorm(dim, dim)
        self.attn = SelfAttention(dim, heads, rope_base)
        self.norm2 = ModulatedLayerNorm(dim, dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, cond: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.attn(self.norm1(x, cond), pos)
        return x + self.mlp(self.norm2(x, cond))
