"""The training objective of paper section 4.1: L = l_pose L_pose + l_geo L_geo + L_render (eq. 8-11).

Every loss takes batched tensors for one frame (or a sequence stacked on the first dimension) and returns a scalar
averaged over the batch, so the per-frame terms can be summed over a sequence as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from worker.geometry import rotmat_to_quat, sim3_decompose


def pose_loss(pred_c2w: torch.Tensor, gt_c2w: torch.Tensor) -> torch.Tensor:
    """Eq. 9: ||q_hat - q|| + ||t_hat - t||, quaternions wxyz with w >= 0 (the sign ambiguity removed).

    pred_c2w, gt_c2w: [B,4,4] camera-to-world poses in the frame of the sequence's first frame.
    """
    q_pred = rotmat_to_quat(pred_c2w[..., :3, :3])
    q_gt = rotmat_to_quat(gt_c2w[..., :3, :3])
    t_err = (pred_c2w[..., :3, 3] - gt_c2w[..., :3, 3]).norm(dim=-1)
    return ((q_pred - q_gt).norm(dim=-1) + t_err).mean()


def geometry_loss(
    points: torch.Tensor, conf: torch.Tensor, gt_points: torch.Tensor, valid: torch.Tensor, alpha: float = 0.2
) -> torch.Tensor:
    """Eq. 10: confidence-weighted point error minus alpha log c, averaged over valid pixels.

    points, gt_points: [B,H,W,3]; conf: [B,H,W] (> 0); valid: [B,H,W] bool (ground-truth depth present).
    """
    err = (points - gt_points).norm(dim=-1)
    per_pixel = conf * err - alpha * torch.log(conf)
    mask = valid.to(per_pixel.dtype)
    return (per_pixel * mask).sum() / mask.sum().clamp_min(1.0)


def _gaussian_window(size: int, sigma: float, channels: int, like: torch.Tensor) -> torch.Tensor:
    coords = torch.arange(size, dtype=like.dtype, device=like.device) - (size - 1) / 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(image: torch.Tensor, reference: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of [B,H,W,C] images in [0,1] (11x11 Gaussian window, sigma 1.5, zero padding, C1/C2 for L = 1)."""
    x = image.permute(0, 3, 1, 2)
    y = reference.permute(0, 3, 1, 2)
    channels = x.shape[1]
    w = _gaussian_window(window, sigma, channels, x)
    pad = window // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, w, padding=pad, groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return value.mean()


@dataclass(frozen=True)
class RenderLossWeights:
    """lambda_mse, lambda_perceptual, lambda_depth of eq. 11."""

    mse: float = 1.0
    perceptual: float = 0.05
    depth: float = 0.1


def render_loss(
    rendered_rgb: torch.Tensor,
    rendered_depth: torch.Tensor,
    gt_rgb: torch.Tensor,
    gt_depth: torch.Tensor,
    weights: RenderLossWeights = RenderLossWeights(),
    perceptual=None,
) -> torch.Tensor:
    """Eq. 11 for one batch of frames: MSE + perceptual term + squared depth error on valid depth.

    rendered_rgb, gt_rgb: [B,H,W,3] in [0,1]; rendered_depth, gt_depth: [B,H,W] (gt 0 = invalid).
    `perceptual(a, b) -> scalar` is LPIPS when its weights are present; None substitutes 1 - SSIM.
    """
    mse = F.mse_loss(rendered_rgb, gt_rgb)
    perceptual_term = perceptual(rendered_rgb, gt_rgb) if perceptual is not None else 1.0 - ssim(rendered_rgb, gt_rgb)
    valid = (gt_depth > 0).to(rendered_depth.dtype)
    depth = (((rendered_depth - gt_depth) ** 2) * valid).sum() / valid.sum().clamp_min(1.0)
    return weights.mse * mse + weights.perceptual * perceptual_term + weights.depth * depth


def scale_of(c2w: torch.Tensor) -> torch.Tensor:
    """Similarity scale of [...,4,4] poses (1 for SE(3))."""
    return sim3_decompose(c2w)[0]
