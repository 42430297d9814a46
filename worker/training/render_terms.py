"""The two rendering losses of appendix D.2: each frame's surfels rendered alone, and the whole clip's surfels
merged into one map and rendered from every frame."""

from __future__ import annotations

import torch

from worker.frontend.types import StepOutput
from worker.geometry import sim3_inverse
from worker.mapping import Surfels

from .losses import RenderLossWeights, render_loss


def camera_surfels(out: StepOutput, b: int = 0, stride: int = 1) -> Surfels:
    """Per-pixel surfels of batch element b in its camera frame (every `stride`-th pixel, for cheaper renders)."""

    def take(t: torch.Tensor) -> torch.Tensor:
        t = t[b, ::stride, ::stride]
        return t.reshape(-1, *t.shape[2:]) if t.dim() > 2 else t.reshape(-1)

    means = take(out.points_cam)
    return Surfels(
        means=means,
        quats=take(out.quats),
        scales=take(out.scales) * stride,
        opacities=take(out.opacity),
        colors=take(out.colors),
        keyframe_ids=torch.zeros(means.shape[0], dtype=torch.int64, device=means.device),
    )


def per_frame_render_loss(
    outputs: list[StepOutput],
    images: torch.Tensor,
    depths: torch.Tensor,
    K: torch.Tensor,
    weights: RenderLossWeights,
    perceptual=None,
    stride: int = 1,
) -> torch.Tensor:
    """Each frame's predicted surfels rendered from its own (identity) camera against its image and depth.

    images: [L,B,H,W,3] in [0,1]; depths: [L,B,H,W]; K: [3,3] at the model resolution.
    """
    from worker.mapping import rasterize

    L, B, H, W = depths.shape
    eye = torch.eye(4, dtype=images.dtype, device=images.device)
    total = images.new_zeros(())
    for t, out in enumerate(outputs):
        for b in range(B):
            r = rasterize(camera_surfels(out, b, stride), eye, K, W, H)
            total = total + render_loss(r.rgb[None], r.depth[None], images[t, b][None], depths[t, b][None],
                                        weights, perceptual)
    return total / (L * B)


def merged_render_loss(
    outputs: list[StepOutput],
    images: torch.Tensor,
    depths: torch.Tensor,
    gt_c2w: torch.Tensor,
    K: torch.Tensor,
    weights: RenderLossWeights,
    perceptual=None,
    stride: int = 2,
) -> torch.Tensor:
    """All frames' surfels placed by their predicted poses, merged, and rendered from every ground-truth view.

    gt_c2w: [L,B,4,4] in the frame of the clip's first frame (the same frame the predicted poses live in).
    """
    from worker.mapping import rasterize

    L, B, H, W = depths.shape
    total = images.new_zeros(())
    for b in range(B):
        merged = Surfels.concat([camera_surfels(out, b, stride).transform(out.pose_c2w[b]) for out in outputs])
        for t in range(L):
            r = rasterize(merged, sim3_inverse(gt_c2w[t, b]), K, W, H)
            total = total + render_loss(r.rgb[None], r.depth[None], images[t, b][None], depths[t, b][None],
                                        weights, perceptual)
    return total / (L * B)
