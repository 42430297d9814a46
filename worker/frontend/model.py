"""The recurrent feed-forward frontend f(I_t, M_{t-1}) -> (T_t, G_t, M_t) of paper section 4.1 (CUT3R-style).

Parameter names equal CUT3R's (plus the 2DGS head), so a CUT3R checkpoint loads by name (see cut3r_import.py).
"""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from .blocks import LN_EPS, DecoderBlock, EncoderBlock
from .configs import FrontendConfig, get_config
from .decoders import PoseRetriever, run_interleaved_decoders
from .encoder import PatchEmbed, state_positions
from .heads import DownstreamHead
from .types import HiddenState, StepOutput

PRECISIONS = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}


class FeedForwardModel(nn.Module):
    """ViT encoder, learned state and pose memory, two interleaved decoders, DPT/2DGS/pose heads."""

    def __init__(self, config: FrontendConfig) -> None:
        super().__init__()
        c = self.config = config
        self.precision = "fp32"
        # Encoder (paper Table 7 "Encoder").
        self.patch_embed = PatchEmbed(3, c.enc_dim, c.patch_size)
        self.enc_blocks = nn.ModuleList(
            EncoderBlock(c.enc_dim, c.enc_heads, c.mlp_ratio, c.rope_base) for _ in range(c.enc_depth)
        )
        self.enc_norm = nn.LayerNorm(c.enc_dim, eps=LN_EPS)
        # Ray-map branch (CUT3R's optional query/conditioning input; kept so its weights load and can be used).
        self.patch_embed_ray_map = PatchEmbed(6, c.enc_dim, c.patch_size)
        self.enc_blocks_ray_map = nn.ModuleList(
            EncoderBlock(c.enc_dim, c.enc_heads, c.mlp_ratio, c.rope_base) for _ in range(c.ray_enc_depth)
        )
        self.enc_norm_ray_map = nn.LayerNorm(c.enc_dim, eps=LN_EPS)
        self.masked_img_token = nn.Parameter(torch.randn(1, c.enc_dim) * 0.02)
        self.masked_ray_map_token = nn.Parameter(torch.randn(1, c.enc_dim) * 0.02)
        # Learned tokens.
        self.pose_token = nn.Parameter(torch.randn(1, 1, c.dec_dim) * 0.02)
        self.register_tokens = nn.Embedding(c.state_size, c.enc_dim)
        # Decoders and pose memory (paper Table 7 "Decoder").
        self.decoder_embed = nn.Linear(c.enc_dim, c.dec_dim)
        self.dec_blocks = nn.ModuleList(
            DecoderBlock(c.dec_dim, c.dec_heads, c.mlp_ratio, c.rope_base) for _ in range(c.dec_depth)
        )
        self.dec_norm = nn.LayerNorm(c.dec_dim, eps=LN_EPS)
        self.decoder_embed_state = nn.Linear(c.enc_dim, c.dec_dim)
        self.dec_blocks_state = nn.ModuleList(
            DecoderBlock(c.dec_dim, c.state_dec_heads, c.mlp_ratio, c.rope_base) for _ in range(c.dec_depth)
        )
        self.dec_norm_state = nn.LayerNorm(c.dec_dim, eps=LN_EPS)
        self.pose_retriever = PoseRetriever(c.enc_dim, c.dec_dim, c.memory_size, c.memory_heads, c.memory_depth,
                                            c.mlp_ratio)
        self.downstream_head = DownstreamHead(c)
        self._init_weights()
        # Conv weights in channels_last: about 2x faster DPT heads with oneDNN (CPU) and cuDNN.
        self.downstream_head.to(memory_format=torch.channels_last)

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        # Zero-initialised adapter output: the GS head starts from the shared tokens.
        nn.init.zeros_(self.downstream_head.gs_adapter.fc2.weight)
        if self.config.color_skip:  # colour residual 0: every surfel starts at its own pixel's colour
            colour_out = self.downstream_head.dpt_gs.head[-1]
            nn.init.zeros_(colour_out.weight[:3])
            nn.init.zeros_(colour_out.bias[:3])

    # ------------------------------------------------------------------ precision
    def set_precision(self, precision: str) -> FeedForwardModel:
        """'fp32', 'bf16' or 'fp16': autocast dtype for the encoder and decoders (heads always run in fp32)."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        self.precision = precision
        return self

    def _autocast(self, device: torch.device) -> contextlib.AbstractContextManager:
        dtype = PRECISIONS[self.precision]
        if dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(device_type=device.type, dtype=dtype)

    # ------------------------------------------------------------------ state
    def init_state(self, batch: int = 1) -> HiddenState:
        """M0: the learned state tokens projected to the decoder width, and the learned pose memory."""
        if batch < 1:
            raise ValueError("batch must be >= 1")
        tokens = self.decoder_embed_state(self.register_tokens.weight)[None].expand(batch, -1, -1).clone()
        return HiddenState(tokens, self.pose_retriever.initial_memory(batch), frames_seen=0)

    # ------------------------------------------------------------------ encoder
    def _check_image(self, image: torch.Tensor) -> None:
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be [B, 3, H, W], got {tuple(image.shape)}")
        p = self.config.patch_size
        if image.shape[2] % p or image.shape[3] % p:
            raise ValueError(f"image height and width must be multiples of {p}, got {tuple(image.shape[2:])}")
        if not image.is_floating_point():
            raise ValueError("image must be a float tensor in [0, 1]")

    def encode_image(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Encoder tokens [B, N, E] (after the final norm) and their (row, col) positions [B, N, 2]."""
        self._check_image(image)
        with self._autocast(image.device):
            x, pos = self.patch_embed(image * 2.0 - 1.0)
            for block in self.enc_blocks:
                x = block(x, pos)
            return self.enc_norm(x), pos

    def encode_ray_map(self, ray_map: torch.Tensor) -> torch.Tensor:
        """Tokens [B, N, E] of a ray map [B, H, W, 6] (camera centre, ray direction), CUT3R's query input."""
        if ray_map.ndim != 4 or ray_map.shape[-1] != 6:
            raise ValueError(f"ray_map must be [B, H, W, 6], got {tuple(ray_map.shape)}")
        x, pos = self.patch_embed_ray_map(ray_map.permute(0, 3, 1, 2))
        for block in self.enc_blocks_ray_map:
            x = block(x, pos)
        return self.enc_norm_ray_map(x)

    # ------------------------------------------------------------------ step
    def step(self, image: torch.Tensor, state: HiddenState, update: bool = True,
             ray_map: torch.Tensor | None = None) -> StepOutput:
        """One frame: image [B, 3, H, W] in [0, 1] and M_{t-1} -> StepOutput (with M_t, or M_{t-1} if not update).

        `ray_map` [B, H, W, 6] optionally adds CUT3R's ray-map tokens to the image tokens.
        """
        B, _, H, W = image.shape
        if state.state_tokens.shape[0] != B or state.pose_memory.shape[0] != B:
            raise ValueError(f"state batch {state.state_tokens.shape[0]} does not match image batch {B}")
        c = self.config
        p = c.patch_size
        tokens, pos = self.encode_image(image)
        with self._autocast(image.device):
            if ray_map is not None:
                tokens = tokens + self.encode_ray_map(ray_map.to(tokens.dtype))
            pooled = tokens.mean(dim=1, keepdim=True)
            memory = state.pose_memory
            if state.frames_seen == 0:
                pose_token = self.pose_token.expand(B, -1, -1)
            else:
                pose_token = self.pose_retriever.read(pooled, memory)
            image_stream = torch.cat((pose_token.to(tokens.dtype), self.decoder_embed(tokens)), dim=1)
            pose_pos = torch.full((B, 1, 2), -1, dtype=pos.dtype, device=pos.device)
            image_pos = torch.cat((pose_pos, pos), dim=1)
            s_pos = state_positions(c.state_size, image.device).expand(B, -1, -1)
            layers, new_state = run_interleaved_decoders(
                self.dec_blocks, self.dec_blocks_state, image_stream, image_pos, state.state_tokens, s_pos)
            final = self.dec_norm(layers[-1])
            new_state = self.dec_norm_state(new_state)
            pose_out = final[:, :1]
            if update:
                new_memory = self.pose_retriever.write(memory, pooled, pose_out)
        a, b, _ = c.dpt_hooks
        features = [tokens, layers[a - 1][:, 1:], layers[b - 1][:, 1:], final[:, 1:]]
        heads = self.downstream_head(features, pose_out[:, 0], pos, (H // p, W // p), image)
        if update:
            dtype = state.state_tokens.dtype
            next_state = HiddenState(new_state.to(dtype), new_memory.to(dtype), state.frames_seen + 1)
        else:
            next_state = state
        return StepOutput(
            pose_c2w=heads.pose_c2w, points_cam=heads.points_cam, conf=heads.conf, points_world=heads.points_world,
            conf_world=heads.conf_world, opacity=heads.opacity, quats=heads.quats, scales=heads.scales,
            colors=heads.colors, state=next_state,
        )

    def forward(self, image: torch.Tensor, state: HiddenState, update: bool = True) -> StepOutput:
        return self.step(image, state, update)

    def compile_step(self, height: int, width: int, precision: str = "bf16"):
        """An AcceleratedStepper: CUDA-graph replay of batch-1 steps at height x width (plain `step` on CPU)."""
        from .accelerate import AcceleratedStepper

        return AcceleratedStepper(self, height, width, precision)


def build_model(name: str | FrontendConfig = "tiny", device: torch.device | str = "cpu") -> FeedForwardModel:
    """Build the named model (`tiny`, `small`, `base`, `paper`, or a FrontendConfig) on `device` in eval mode.

    device="meta" builds the structure without allocating weights (e.g. to count the paper model's parameters).
    """
    config = name if isinstance(name, FrontendConfig) else get_config(name)
    with torch.device(device):
        model = FeedForwardModel(config)
    return model.eval()
