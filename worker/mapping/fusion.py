"""Map fusion (paper sec. 4.3): prune surfels that explain a new keyframe badly, add new ones where the map is thin.

Per-primitive error attribution. For pruning we need, per surfel i, the blending weight it puts on badly
reconstructed pixels, W_bad(i) = sum over bad pixels p of w_ip, and on all pixels, W_all(i). The rendered colour is
linear in the colours (rgb_p = sum_i w_ip c_i + T_p bg), so d(sum_p m_p rgb_p[ch]) / d c_i[ch] = sum_p m_p w_ip
exactly. One render with only the colours requiring grad, followed by one backward of
sum_p bad_p rgb_p[0] + sum_p rgb_p[1], yields both sums for every surfel. This reuses the differentiable rasterizer
unchanged (no extra id/weight render mode), is exact rather than a top-k approximation, and the same forward pass
also gives the rgb, depth and accumulation maps used to find the bad pixels; the backward is cheap because no
geometry attribute requires grad.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from worker.geometry import project_points

from .rasterize import RenderResult, rasterize
from .surfels import Surfels


@dataclass(frozen=True)
class FusionThresholds:
    """Thresholds of pruning and densification (the paper does not give values; these are ours)."""

    rgb_error: float = 0.25  # a pixel is bad when its mean absolute RGB error exceeds this
    depth_error: float = 0.1  # ... or its depth error exceeds this fraction of the reference depth
    min_alpha: float = 0.5  # only pixels the map covers at least this much are judged
    prune_weight: float = 0.5  # prune surfels with at least this much blending weight (pixel units) on bad pixels
    prune_fraction: float = 0.5  # ... that is at least this fraction of all their weight in this view
    tau_accum: float = 0.7  # new surfels are added only where the map's accumulation is below this


@dataclass
class ErrorAttribution:
    """The map's render from one view, its bad-pixel mask, and per-surfel weights on bad / all pixels."""

    render: RenderResult
    bad_pixels: torch.Tensor  # [H, W] bool
    bad_weight: torch.Tensor  # [N]
    total_weight: torch.Tensor  # [N]


def bad_pixel_mask(render: RenderResult, image: torch.Tensor, depth: torch.Tensor | None,
                   thresholds: FusionThresholds, depth_scale: float = 1.0) -> torch.Tensor:
    """Pixels the map covers whose RGB (or depth, when a reference depth is given) error is high.

    `depth_scale` converts the render's depth to the reference's units (reference = render / depth_scale).
    """
    covered = render.alpha > thresholds.min_alpha
    rgb_err = (render.rgb.clamp(0, 1) - image).abs().mean(-1)
    bad = rgb_err > thresholds.rgb_error
    if depth is not None:
        ref_ok = depth > 0
        rendered = render.depth / depth_scale
        bad |= ref_ok & ((rendered - depth).abs() > thresholds.depth_error * depth)
    return bad & covered


def attribute_errors(surfels: Surfels, viewmat: torch.Tensor, K: torch.Tensor, image: torch.Tensor,
                     depth: torch.Tensor | None, thresholds: FusionThresholds,
                     depth_scale: float = 1.0) -> ErrorAttribution:
    """Render `surfels` from `viewmat` and attribute the high-error pixels to the surfels blending into them."""
    H, W = image.shape[:2]
    colors = surfels.colors.detach().clone().requires_grad_(True)
    probe = Surfels(surfels.means.detach(), surfels.quats.detach(), surfels.scales.detach(),
                    surfels.opacities.detach(), colors, surfels.keyframe_ids)
    with torch.enable_grad():
        render = rasterize(probe, viewmat, K, W, H, background=torch.zeros(3, dtype=colors.dtype, device=colors.device))
        bad = bad_pixel_mask(_detached(render), image, depth, thresholds, depth_scale)
        objective = (render.rgb[..., 0] * bad).sum() + render.rgb[..., 1].sum()
        (grad,) = torch.autograd.grad(objective, colors, allow_unused=True)
    if grad is None:  # nothing visible
        grad = torch.zeros_like(colors)
    return ErrorAttribution(_detached(render), bad, grad[:, 0].detach(), grad[:, 1].detach())


def prune_mask(attribution: ErrorAttribution, thresholds: FusionThresholds) -> torch.Tensor:
    """[N] bool: surfels to remove (significant weight, mostly on bad pixels)."""
    bad, total = attribution.bad_weight, attribution.total_weight
    return (bad >= thresholds.prune_weight) & (bad >= thresholds.prune_fraction * total.clamp_min(1e-12))


def densify_mask(surfels_cam: Surfels, K: torch.Tensor, accumulation: torch.Tensor, tau_accum: float) -> torch.Tensor:
    """[N] bool: camera-frame surfels to add, i.e. those landing on pixels whose accumulation is below tau_accum.

    Surfels projecting outside the image are added (the map has no evidence there); surfels behind the camera
    are not.
    """
    H, W = accumulation.shape
    uv, z = project_points(surfels_cam.means, K.to(surfels_cam.means.dtype))
    col = torch.floor(uv[:, 0]).long()
    row = torch.floor(uv[:, 1]).long()
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    acc = torch.zeros_like(z)
    acc[inside] = accumulation[row[inside], col[inside]].to(z.dtype)
    return (z > 0) & (~inside | (acc < tau_accum))


def _detached(render: RenderResult) -> RenderResult:
    return RenderResult(*(t.detach() for t in render))
