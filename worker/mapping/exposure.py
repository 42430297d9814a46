"""Per-keyframe affine exposure: a photo is `gain * radiance + bias`, per colour channel.

Auto-exposure and white balance change between a camera's frames; a map trained on the raw photos bakes those
changes into its colours (blotches where keyframes disagree). The map instead keeps exposure-normalised colours:
each keyframe has an exposure (gain [3], bias [3]: a [6] tensor, identity = gain 1, bias 0), the refinement
compares `apply_exposure(render, exposure)` to the keyframe's photo, and renders at a given pose use the
normalised colours (identity exposure). The first keyframe's exposure stays the identity (it fixes the map's
colour scale).

An exposure is estimated in closed form: per channel, the ridge regression of the photo on the render over the
pixels the map covers, pulled toward the identity with a weight of `prior` times the pixel count (it decides the
exposure when few pixels are covered or the covered ones have no contrast), then shrunk toward the identity by a
threshold (`shrink_exposure`): changes of a few per cent are what view-dependent shading alone makes between two
views of a surface, and normalising them away compounds from keyframe to keyframe (bench/RESULTS.md, issue 21).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

GAIN_RANGE = (0.2, 5.0)
BIAS_RANGE = (-0.5, 0.5)
SATURATED = 0.005  # photo values this close to 0 or 1 are clipped
BLOCK = 8  # exposures are fitted on block x block averages
MIN_BLOCKS_ACROSS = 30
BIAS_PRIOR = 1.0  # pull of the bias toward 0, as a fraction of the pixels (see fit_exposure)


def identity_exposure(device: torch.device | str = "cpu") -> torch.Tensor:
    """[6] float32: gain (1, 1, 1) then bias (0, 0, 0)."""
    return torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], device=device)


def apply_exposure(image: torch.Tensor, exposure: torch.Tensor) -> torch.Tensor:
    """The photo a camera with `exposure` takes of normalised colours `image` [..., 3]."""
    return image * exposure[:3] + exposure[3:]


def remove_exposure(image: torch.Tensor, exposure: torch.Tensor) -> torch.Tensor:
    """Normalised colours [..., 3] of a photo taken with `exposure` (the inverse of `apply_exposure`)."""
    return (image - exposure[3:]) / exposure[:3]


def shrink_exposure(exposure: torch.Tensor, threshold: float) -> torch.Tensor:
    """`exposure` [6] pulled toward the identity by the non-negative garrote: a log gain l becomes
    l - threshold^2 / l, or 0 when |l| <= threshold (a bias b likewise, with threshold / 2): changes within the
    threshold vanish, large ones stay nearly whole, and the result is continuous in the fit."""
    if threshold <= 0:
        return exposure
    log_gain = torch.log(exposure[:3])
    return torch.cat([torch.exp(_garrote(log_gain, threshold)), _garrote(exposure[3:], threshold / 2)])


def _garrote(x: torch.Tensor, threshold: float) -> torch.Tensor:
    return torch.where(x.abs() > threshold, x - threshold**2 / torch.where(x == 0, 1.0, x), torch.zeros_like(x))


def fit_exposure(render: torch.Tensor, photo: torch.Tensor, mask: torch.Tensor, prior: float = 0.002,
                 block: int = BLOCK, bias_prior: float = BIAS_PRIOR, threshold: float = 0.0) -> torch.Tensor | None:
    """[6] exposure minimising, per channel, sum over `mask` of (gain * render + bias - photo)^2 +
    count * (prior * (gain - 1)^2 + bias_prior * bias^2).

    The bias is held near 0 much more firmly than the gain: over the narrow range of colours a view often holds,
    a gain change and a bias change explain the photo almost alike (on ICL with a simulated auto-exposure, equal
    priors traded 0.1 of gain for 0.1 of bias), and cameras change exposure mostly by a factor.

    render, photo: [H, W, 3] in [0, 1]; mask: [H, W] bool (pixels the render covers). A channel's saturated photo
    values (within SATURATED of 0 or 1: clipped, so not affine in the radiance) take no part; None when no pixel
    is left. Gains are kept in GAIN_RANGE and biases in BIAS_RANGE, then shrunk toward the identity by
    `threshold` (`shrink_exposure`).

    The fit runs on `block` x `block` averages (blocks the mask covers entirely): a render is smoother than the
    photo, and regressing a sharp photo on a smoother render inflates the gain (and lowers the bias) even when the
    exposures are equal; block averages of both have the same sharpness. A block takes part only where each of its
    pixels does.
    """
    photo = photo.detach().to(render.dtype)
    usable = mask[..., None] & (photo > SATURATED) & (photo < 1 - SATURATED)  # [H, W, 3]
    usable = _blocks(usable.to(render.dtype), block) > 0.999  # blocks whose every pixel is usable
    if not bool(usable.any()):
        return None
    r = _blocks(render.detach(), block).reshape(-1, 3).to(torch.float64)
    t = _blocks(photo, block).reshape(-1, 3).to(torch.float64)
    w = usable.reshape(-1, 3).to(torch.float64)
    n = w.sum(0)
    lam, lam_bias = prior * n, bias_prior * n
    s_rr, s_r, s_rt, s_t = (w * r * r).sum(0), (w * r).sum(0), (w * r * t).sum(0), (w * t).sum(0)
    # Normal equations [[s_rr + lam, s_r], [s_r, n + lam_bias]] [gain, bias] = [s_rt + lam, s_t], per channel.
    a, b, d = s_rr + lam, s_r, n + lam_bias
    det = (a * d - b * b).clamp_min(1e-12)
    gain = torch.where(n > 0, ((s_rt + lam) * d - b * s_t) / det, 1.0)
    bias = torch.where(n > 0, (a * s_t - b * (s_rt + lam)) / det, 0.0)
    exposure = torch.cat([gain.clamp(*GAIN_RANGE), bias.clamp(*BIAS_RANGE)])
    return shrink_exposure(exposure, threshold).to(render.device, torch.float32)


def _blocks(image: torch.Tensor, block: int) -> torch.Tensor:
    """[H, W, C] averaged over block x block tiles (fewer pixels per tile in small images: at least
    MIN_BLOCKS_ACROSS tiles along the shorter side)."""
    block = max(1, min(block, min(image.shape[:2]) // MIN_BLOCKS_ACROSS))
    if block == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], block)[0].permute(1, 2, 0)
