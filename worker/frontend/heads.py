"""Output heads: DPT adapters (camera-frame means, world-frame means, 2DGS attributes), adaLN final transform,
pose MLP, and the output activations (expm1 radial map, conf = 1 + e^x, exp-mapped pose)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from worker.geometry import quat_normalize, quat_to_rotmat

from .blocks import Mlp, ModulatedBlock
from .configs import GAUSSIAN_CHANNELS, FrontendConfig

# Pixel footprint prior for surfel scales: CUT3R's base focal max(H, W) / (2 tan 30 deg).
_BASE_FOCAL_FACTOR = 1.0 / (2.0 * math.tan(math.radians(30.0)))


def _upsample2(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class ResidualConvUnit(nn.Module):
    """x + Conv3x3(ReLU(Conv3x3(ReLU(x))))."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(dim, dim, 3, padding=1)
        self.conv2 = nn.Conv2d(dim, dim, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """DPT refinement: (path + RCU1(skip)) -> RCU2 -> x2 bilinear -> 1x1 conv."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(dim)
        self.resConfUnit2 = ResidualConvUnit(dim)
        self.out_conv = nn.Conv2d(dim, dim, 1)

    def forward(self, path: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        if skip is not None:
            path = path + self.resConfUnit1(skip)
        return self.out_conv(_upsample2(self.resConfUnit2(path)))


class DPTScratch(nn.Module):
    """Projection of the four reassembled maps to a common width and the four fusion blocks."""

    def __init__(self, layer_dims: tuple[int, ...], dim: int) -> None:
        super().__init__()
        for i, c in enumerate(layer_dims, start=1):
            setattr(self, f"layer{i}_rn", nn.Conv2d(c, dim, 3, padding=1, bias=False))
        for i in range(1, 5):
            setattr(self, f"refinenet{i}", FusionBlock(dim))


class DPTAdapter(nn.Module):
    """DPT head over four token maps [enc tokens, dec a, dec b, dec last] of a (h, w) patch grid -> [B, C, 16h, 16w].

    The first map is expected at `token_dims[0]` channels (encoder width), the others at `token_dims[1]`.
    """

    def __init__(self, token_dims: tuple[int, int], layer_dims: tuple[int, int, int, int], feature_dim: int,
                 last_dim: int, out_channels: int) -> None:
        super().__init__()
        enc_dim, dec_dim = token_dims
        l1, l2, l3, l4 = layer_dims
        self.act_postprocess = nn.ModuleList([
            nn.Sequential(nn.Conv2d(enc_dim, l1, 1), nn.ConvTranspose2d(l1, l1, 4, stride=4)),
            nn.Sequential(nn.Conv2d(dec_dim, l2, 1), nn.ConvTranspose2d(l2, l2, 2, stride=2)),
            nn.Sequential(nn.Conv2d(dec_dim, l3, 1)),
            nn.Sequential(nn.Conv2d(dec_dim, l4, 1), nn.Conv2d(l4, l4, 3, stride=2, padding=1)),
        ])
        self.scratch = DPTScratch(layer_dims, feature_dim)
        self.head = nn.Sequential(
            nn.Conv2d(feature_dim, feature_dim // 2, 3, padding=1),
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True),
            nn.Conv2d(feature_dim // 2, last_dim, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(last_dim, out_channels, 1),
        )

    def forward(self, tokens: list[torch.Tensor], grid: tuple[int, int]) -> torch.Tensor:
        h, w = grid
        # channels_last makes oneDNN's convolutions about 2x faster for these thin feature maps on CPU.
        maps = [t.transpose(1, 2).reshape(t.shape[0], t.shape[2], h, w).contiguous(memory_format=torch.channels_last)
                for t in tokens]
        l1, l2, l3, l4 = (post(m) for post, m in zip(self.act_postprocess, maps, strict=True))
        s = self.scratch
        l1, l2, l3, l4 = s.layer1_rn(l1), s.layer2_rn(l2), s.layer3_rn(l3), s.layer4_rn(l4)
        path = s.refinenet4(l4)[:, :, : l3.shape[2], : l3.shape[3]]
        path = s.refinenet3(path, l3)
        path = s.refinenet2(path, l2)
        path = s.refinenet1(path, l1)
        return self.head(path)


class PoseHead(nn.Module):
    """MLP from the output pose token to the raw 7-vector (translation 3, quaternion wxyz 4)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.mlp = Mlp(dim, 4 * dim, 7)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.mlp(z)


def radial_expm1(raw: torch.Tensor) -> torch.Tensor:
    """r / |r| * (e^|r| - 1): CUT3R's 'exp' map for points and translations (channels last)."""
    d = raw.norm(dim=-1, keepdim=True)
    return raw / d.clamp_min(1e-8) * torch.expm1(d)


def pose_from_raw(raw: torch.Tensor) -> torch.Tensor:
    """Camera-to-world SE(3) [B, 4, 4] from the raw pose vector [B, 7]."""
    t = radial_expm1(raw[:, :3])
    q = quat_normalize(raw[:, 3:7])
    q = torch.where(q[:, :1] < 0, -q, q)
    pose = torch.eye(4, dtype=raw.dtype, device=raw.device).repeat(raw.shape[0], 1, 1)
    pose[:, :3, :3] = quat_to_rotmat(q)
    pose[:, :3, 3] = t
    return pose


@dataclass
class HeadOutputs:
    pose_c2w: torch.Tensor
    points_cam: torch.Tensor
    conf: torch.Tensor
    points_world: torch.Tensor
    conf_world: torch.Tensor
    opacity: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    colors: torch.Tensor


# Pixel colours are clamped away from 0 and 1 before the logit so a saturated pixel stays reachable by the residual.
_COLOR_LOGIT_EPS = 1e-3


def gaussian_attributes(raw: torch.Tensor, points_cam: torch.Tensor, image: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, ...]:
    """(colors [0,1], opacity (0,1), quats wxyz unit with w >= 0, scales > 0) from the GS DPT's channels-last output.

    With `image` ([B,H,W,3] in [0,1], the input frame at the head's resolution) the colour is a residual on the
    pixel's own colour, sigmoid(logit(pixel) + raw); without it, sigmoid(raw). Rotation is biased towards identity
    (a surfel facing the camera); scales are relative to the pixel footprint |mu| / f0 with CUT3R's base focal
    f0 = max(H, W) / (2 tan 30 deg).
    """
    H, W = raw.shape[1:3]
    color_raw = raw[..., 0:3]
    if image is not None:
        color_raw = color_raw + torch.logit(image.to(raw.dtype), eps=_COLOR_LOGIT_EPS)
    colors = torch.sigmoid(color_raw)
    opacity = torch.sigmoid(raw[..., 3])
    identity = torch.zeros(4, dtype=raw.dtype, device=raw.device)
    identity.narrow(0, 0, 1).fill_(1.0)  # a fill kernel, not a host-to-device copy: keeps CUDA-graph capture legal
    quats = quat_normalize(raw[..., 4:8] + identity)
    quats = torch.where(quats[..., :1] < 0, -quats, quats)
    footprint = points_cam.norm(dim=-1, keepdim=True).clamp_min(1e-6) / (_BASE_FOCAL_FACTOR * max(H, W))
    scales = torch.exp(raw[..., 8:10].clamp(max=20.0)) * footprint
    return colors, opacity, quats, scales


class DownstreamHead(nn.Module):
    """Everything after the decoders. Runs in fp32 whatever the decoders' precision."""

    def __init__(self, config: FrontendConfig) -> None:
        super().__init__()
        c = config
        self.color_skip = c.color_skip
        token_dims = (c.enc_dim, c.dec_dim)
        dpt = dict(layer_dims=c.dpt_layer_dims, feature_dim=c.dpt_feature_dim, last_dim=c.dpt_last_dim)
        self.pose_head = PoseHead(c.dec_dim)
        self.final_transform = nn.ModuleList(
            ModulatedBlock(c.dec_dim, c.dec_heads, c.mlp_ratio, c.rope_base) for _ in range(c.final_transform_depth)
        )
        self.dpt_self = DPTAdapter(token_dims, out_channels=4, **dpt)
        self.dpt_cross = DPTAdapter(token_dims, out_channels=4, **dpt)
        self.dpt_gs = DPTAdapter(token_dims, out_channels=GAUSSIAN_CHANNELS, **dpt)
        self.gs_adapter = Mlp(c.dec_dim, c.gs_adapter_hidden)
        nn.init.zeros_(self.gs_adapter.fc2.weight)
        nn.init.zeros_(self.gs_adapter.fc2.bias)

    def forward(self, features: list[torch.Tensor], pose_token: torch.Tensor, patch_pos: torch.Tensor,
                grid: tuple[int, int], image: torch.Tensor | None = None) -> HeadOutputs:
        """features: [encoder tokens, decoder layer a, decoder layer b, final tokens] without the pose token.

        image: the input frame [B,3,H,W] in [0,1] at the heads' output resolution; required with `color_skip`.
        """
        if self.color_skip and image is None:
            raise ValueError("this model's colour head (color_skip) needs the input image")
        device_type = pose_token.device.type
        with torch.autocast(device_type=device_type, enabled=False):
            features = [f.float() for f in features]
            z = pose_token.float()
            tokens = features[3]
            pose = pose_from_raw(self.pose_head(z))

            self_out = self.dpt_self(features, grid).permute(0, 2, 3, 1).contiguous()
            points_cam, conf = radial_expm1(self_out[..., :3]), 1.0 + torch.exp(self_out[..., 3])

            world_tokens = tokens
            for block in self.final_transform:
                world_tokens = block(world_tokens, z, patch_pos)
            cross_out = self.dpt_cross(features[:3] + [world_tokens], grid).permute(0, 2, 3, 1).contiguous()
            points_world, conf_world = radial_expm1(cross_out[..., :3]), 1.0 + torch.exp(cross_out[..., 3])

            gs_tokens = tokens + self.gs_adapter(tokens)
            gs_out = self.dpt_gs(features[:3] + [gs_tokens], grid).permute(0, 2, 3, 1).contiguous()
            pixels = image.float().permute(0, 2, 3, 1) if self.color_skip else None
            colors, opacity, quats, scales = gaussian_attributes(gs_out, points_cam, pixels)
        return HeadOutputs(pose, points_cam, conf, points_world, conf_world, opacity, quats, scales, colors)
