"""Differentiable image losses for map refinement: L1, SSIM (11x11 Gaussian, sigma 1.5), masked depth L1."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@functools.lru_cache(maxsize=8)
def _gaussian_1d(size: int, sigma: float, dtype: torch.dtype, device: str) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _gaussian_blur(x: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of [1, C, H, W] with zero padding (two 1-D depthwise convs: much faster on CPU)."""
    C = x.shape[1]
    g = _gaussian_1d(size, sigma, x.dtype, str(x.device))
    pad = size // 2
    x = F.conv2d(x, g.view(1, 1, 1, size).expand(C, 1, 1, size), padding=(0, pad), groups=C)
    return F.conv2d(x, g.view(1, 1, size, 1).expand(C, 1, size, 1), padding=(pad, 0), groups=C)


def ssim(image: torch.Tensor, target: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images in [0,1] (11x11 Gaussian window, zero padding, as in the 3DGS/2DGS code)."""
    if image.shape != target.shape or image.ndim != 3:
        raise ValueError(f"ssim needs two [H,W,C] images of equal shape, got {tuple(image.shape)}, "
                         f"{tuple(target.shape)}")
    x = image.permute(2, 0, 1)[None]
    y = target.to(image.dtype).permute(2, 0, 1)[None]
    mu_x, mu_y, xx, yy, xy = _gaussian_blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), window_size,
                                            sigma).chunk(5, dim=1)
    var_x = xx - mu_x**2
    var_y = yy - mu_y**2
    cov = xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (num / den).mean()


def downsample(image: torch.Tensor, factor: int) -> torch.Tensor:
    """[H,W,C] image averaged over factor x factor blocks (trailing rows/columns that do not fill a block dropped)."""
    if factor == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)


def photometric_loss(image: torch.Tensor, target: torch.Tensor, lambda_ssim: float = 0.2,
                     ssim_downsample: int = 1) -> torch.Tensor:
    """(1 - lambda) * L1 + lambda * (1 - SSIM) of [H,W,3] images.

    `ssim_downsample` > 1 computes the SSIM term on block-averaged copies of both images (factor^2 cheaper; L1 stays
    at full resolution).
    """
    if int(ssim_downsample) != ssim_downsample or ssim_downsample < 1:
        raise ValueError(f"ssim_downsample must be a positive integer, got {ssim_downsample}")
    l1 = (image - target).abs().mean()
    if lambda_ssim == 0:
        return l1
    structure = ssim(downsample(image, ssim_downsample), downsample(target.to(image.dtype), ssim_downsample))
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - structure)


def depth_l1(depth: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
             scale: float | torch.Tensor | None = None) -> torch.Tensor:
    """Mean |depth - target| over pixels where target > 0 (and `mask`), divided by `scale`.

    `scale` defaults to the median of the target over those pixels: normalising by the median depth makes the term
    independent of the (monocular) map scale.
    """
    valid = target > 0
    if mask is not None:
        valid &= mask
    if not bool(valid.any()):
        return depth.sum() * 0.0
    if scale is None:
        scale = target[valid].median().clamp_min(1e-6)
    return (depth[valid] - target[valid]).abs().mean() / scale


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0,1] (the render is clamped first)."""
    mse = float(((image.clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
