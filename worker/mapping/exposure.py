"""Per-keyframe affine exposure: a photo is `gain * radiance + bias`, per colour channel.

Auto-exposure and white balance change between a camera's frames; a map trained on the raw photos bakes those
changes into its colours (blotches where keyframes disagree). The map instead keeps exposure-normalised colours:
each keyframe has an exposure (gain [3], bias [3]: a [6] tensor, identity = gain 1, bias 0), the refinement
compares `apply_exposure(render, exposure)` to the keyframe's photo, and renders at a given pose use the
normalised colours (identity exposure). The first keyframe's exposure stays the identity (it fixes the map's
colour scale).

An exposure is estimated in closed form (`fit_exposure`): per channel, the gain is the median over image blocks of
photo / render (the bias is left at 0: cameras change exposure by a factor), then shrunk toward the identity by a
threshold (`shrink_exposure`). Both guard against view-dependent shading, which a per-keyframe gain cannot tell from
exposure: on ICL (constant exposure) glossy and oblique surfaces seen from a new view differ by up to 12 % in blue
from the view that mapped them, while the median block differs by at most 2 %; and a gain fitted to those changes
normalises the keyframe's new surfels with it, so the next keyframe's fit starts from shifted colours and the error
compounds (blue gain 0.88 after eight ICL keyframes with a mean fit; bench/RESULTS.md, issue 21).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

GAIN_RANGE = (0.2, 5.0)
SATURATED = 0.005  # photo values this close to 0 or 1 are clipped
BLOCK = 8  # exposures are fitted on block x block sums
MIN_BLOCKS_ACROSS = 30
MIN_BLOCK_FILL = 0.5  # a block takes part when at least this fraction of its pixels is usable
MIN_BLOCKS = 16  # a channel with fewer usable blocks keeps the identity gain


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
                 block: int = BLOCK, threshold: float = 0.0, shared: bool = False) -> torch.Tensor | None:
    """[6] exposure (gain per channel, bias 0) of `photo` against `render`: per channel, the median over
    `block` x `block` tiles of sum(photo) / sum(render) over the tile's usable pixels, weighed against the identity
    with weight `prior`, kept in GAIN_RANGE and shrunk toward the identity by `threshold` (`shrink_exposure`).
    `shared`: one gain for the three channels, from the tiles' sums over the channels (an exposure change scales
    every channel alike; per-channel gains also follow white balance, and on real footage they drift into hues).

    render, photo: [H, W, 3] in [0, 1]; mask: [H, W] bool (pixels the render covers). A pixel is usable where the
    mask holds and the photo is not saturated (within SATURATED of 0 or 1: clipped, so not proportional to the
    radiance); a tile takes part where at least MIN_BLOCK_FILL of its pixels are usable. The tile sums compare
    the photo and the (smoother) render at the same sharpness; the median leaves out the minority of tiles that
    view-dependent shading (gloss, oblique surfaces) or occlusion edges change. None when no channel has
    MIN_BLOCKS tiles; a channel with fewer keeps the identity gain.
    """
    photo = photo.detach().to(render.dtype)
    usable = (mask[..., None] & (photo > SATURATED) & (photo < 1 - SATURATED)).to(render.dtype)  # [H, W, 3]
    render = render.detach()
    if shared:  # a pixel takes part where every channel is usable; the sums over the channels make one ratio
        usable = usable.amin(-1, keepdim=True)
        render, photo = render.sum(-1, keepdim=True), photo.sum(-1, keepdim=True)
    channels = render.shape[-1]
    fill = _blocks(usable, block)
    render_sum, photo_sum = _blocks(render * usable, block), _blocks(photo * usable, block)
    tiles = (fill >= MIN_BLOCK_FILL) & (render_sum > 1e-3 * fill)  # [h, w, channels]
    counts = tiles.reshape(-1, channels).sum(0)
    if not bool((counts >= MIN_BLOCKS).any()):
        return None
    ratios = (photo_sum / render_sum.clamp_min(1e-12)).reshape(-1, channels)
    gain = torch.ones(channels, dtype=render.dtype, device=render.device)
    for c in range(channels):
        if counts[c] >= MIN_BLOCKS:
            gain[c] = ratios[tiles.reshape(-1, channels)[:, c], c].median()
    gain = ((gain + prior) / (1 + prior)).clamp(*GAIN_RANGE).expand(3)
    exposure = torch.cat([gain, torch.zeros_like(gain)])
    return shrink_exposure(exposure, threshold).to(render.device, torch.float32)


def _blocks(image: torch.Tensor, block: int) -> torch.Tensor:
    """[H, W, C] averaged over block x block tiles (fewer pixels per tile in small images: at least
    MIN_BLOCKS_ACROSS tiles along the shorter side)."""
    block = max(1, min(block, min(image.shape[:2]) // MIN_BLOCKS_ACROSS))
    if block == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], block)[0].permute(1, 2, 0)


def interpolate_exposure(first: torch.Tensor, second: torch.Tensor, weight: float) -> torch.Tensor:
    """[6] exposure a `weight` (0 = `first`, 1 = `second`) of the way between two: the log gains and the biases
    linearly (a camera's auto-exposure moves its gain by factors)."""
    w = min(max(float(weight), 0.0), 1.0)
    log_gain = (1 - w) * torch.log(first[:3]) + w * torch.log(second[:3])
    return torch.cat([torch.exp(log_gain), (1 - w) * first[3:] + w * second[3:]])
