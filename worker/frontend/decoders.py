"""The recurrent core: two interleaved decoders (image stream <-> state) and the pose memory (pose retriever)."""

from __future__ import annotations

import torch
from torch import nn

from .blocks import DecoderBlock


def run_interleaved_decoders(
    image_blocks: nn.ModuleList,
    state_blocks: nn.ModuleList,
    image_tokens: torch.Tensor,
    image_pos: torch.Tensor,
    state_tokens: torch.Tensor,
    state_pos: torch.Tensor,
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Simultaneous bidirectional exchange: layer l updates both streams from layer l-1's outputs only.

    Returns the image stream after every layer (index 0 = layer 1) and the last state stream (not yet normed).
    """
    x, s = image_tokens, state_tokens
    outputs = []
    for image_block, state_block in zip(image_blocks, state_blocks, strict=True):
        s_next = state_block(s, x, state_pos, image_pos)
        x = image_block(x, s, image_pos, state_pos)
        s = s_next
        outputs.append(x)
    return outputs, s


class PoseRetriever(nn.Module):
    """CUT3R's pose memory: M slots of width 2D read to make the pose token and written after every frame."""

    def __init__(self, enc_dim: int, dec_dim: int, memory_size: int, heads: int, depth: int = 2,
                 mlp_ratio: float = 4.0) -> None:
        super().__init__()
        width = 2 * dec_dim
        self.mem = nn.Parameter(torch.randn(1, memory_size, width) * 0.02)
        self.masked_token = nn.Parameter(torch.randn(1, 1, dec_dim) * 0.02)
        self.proj_q = nn.Linear(enc_dim, dec_dim)
        self.read_blocks = nn.ModuleList(DecoderBlock(width, heads, mlp_ratio, rope_base=None) for _ in range(depth))
        self.write_blocks = nn.ModuleList(DecoderBlock(width, heads, mlp_ratio, rope_base=None) for _ in range(depth))

    def initial_memory(self, batch: int) -> torch.Tensor:
        return self.mem.expand(batch, -1, -1).clone()

    def read(self, pooled: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        """Pose token [B, 1, D] retrieved with the mean-pooled encoder tokens [B, 1, E]."""
        q = torch.cat((self.proj_q(pooled), self.masked_token.expand(pooled.shape[0], -1, -1)), dim=-1)
        for block in self.read_blocks:
            q = block(q, memory)
        return q[..., self.masked_token.shape[-1]:]

    def write(self, memory: torch.Tensor, pooled: torch.Tensor, pose_token: torch.Tensor) -> torch.Tensor:
        """The updated memory after seeing the frame's pooled features and its final pose token [B, 1, D]."""
        f = torch.cat((self.proj_q(pooled), pose_token), dim=-1)
        for block in self.write_blocks:
            memory = block(memory, f)
        return memory
