"""Pure-torch 2DGS compositor: the test oracle for the compiled CPU path (differentiable by autograd, any dtype).

"Packed" evaluation: a no-grad pass enumerates every (surfel, pixel) pair gsplat would evaluate (all pixels of the
16x16 tiles the surfel's radius box touches), keeps those with alpha >= 1/255, orders them per pixel front to back;
a differentiable pass then recomputes alpha for the survivors and composites them with a segmented cumulative sum
of log(1 - alpha) (in float64) for the transmittance. The stop rule (a surfel whose next T would be <= 1e-4 is not
added, nor any after it) is a prefix mask, so the result equals gsplat's sequential loop.
"""

from __future__ import annotations

import math

import torch

from .raster_projection import TILE_SIZE
from .raster_tiles import bin_surfels_to_tiles, tile_grid

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
LOWPASS_FILTER = 2.0  # rho_2d = 2 |x - c|^2 (gsplat FILTER_INV_SQUARE_2DGS)
_CANDIDATE_CHUNK = 1 << 21


def surfel_alpha(uv_planes: torch.Tensor, means2d: torch.Tensor, opacities: torch.Tensor,
                 pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Alpha of surfel k at pixel centre pixels[k] (rows aligned), and whether the ray meets its plane (p2 != 0)."""
    x, y = pixels[:, 0:1], pixels[:, 1:2]
    p = x * uv_planes[:, 0] + y * uv_planes[:, 1] + uv_planes[:, 2]
    hits = p[:, 2] != 0
    p2 = torch.where(hits, p[:, 2], torch.ones_like(p[:, 2]))
    u, v = p[:, 0] / p2, p[:, 1] / p2
    rho_3d = u * u + v * v
    delta = pixels - means2d
    rho_2d = LOWPASS_FILTER * (delta * delta).sum(-1)
    rho = torch.where(rho_3d <= rho_2d, rho_3d, rho_2d)
    alpha = torch.clamp_max(opacities * torch.exp(-0.5 * rho), ALPHA_MAX)
    return alpha, hits


def _tile_pixel_offsets(tile_size: int, device: torch.device) -> torch.Tensor:
    r = torch.arange(tile_size, device=device)
    return torch.stack(torch.meshgrid(r, r, indexing="xy"), dim=-1).reshape(-1, 2)  # (dx, dy), row-major


def _candidate_pairs(uv_planes, means2d, opacities, radii, depths, width, height):
    """(surfel [E], pixel [E]) of every contributing-candidate pair (alpha >= 1/255), per pixel front to back."""
    device = means2d.device
    surfel, tile = bin_surfels_to_tiles(means2d, radii, depths, width, height)
    tiles_x, _ = tile_grid(width, height)
    offsets = _tile_pixel_offsets(TILE_SIZE, device)
    per_chunk = max(1, _CANDIDATE_CHUNK // offsets.shape[0])
    kept_surfel, kept_pixel = [], []
    with torch.no_grad():
        for start in range(0, surfel.shape[0], per_chunk):
            s, t = surfel[start:start + per_chunk], tile[start:start + per_chunk]
            origin = torch.stack([t % tiles_x, t // tiles_x], dim=-1) * TILE_SIZE
            px = (origin[:, None, :] + offsets[None]).reshape(-1, 2)
            ss = s[:, None].expand(-1, offsets.shape[0]).reshape(-1)
            inside = (px[:, 0] < width) & (px[:, 1] < height)
            px, ss = px[inside], ss[inside]
            centres = px.to(uv_planes.dtype) + 0.5
            alpha, hits = surfel_alpha(uv_planes[ss], means2d[ss], opacities[ss], centres)
            keep = hits & (alpha >= ALPHA_MIN)
            kept_surfel.append(ss[keep])
            kept_pixel.append(px[keep, 1] * width + px[keep, 0])
    if not kept_surfel:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return empty, empty
    kept_surfel, kept_pixel = torch.cat(kept_surfel), torch.cat(kept_pixel)
    by_pixel = torch.sort(kept_pixel, stable=True).indices  # stable: keeps the per-tile depth order
    return kept_surfel[by_pixel], kept_pixel[by_pixel]


def composite_reference(uv_planes: torch.Tensor, means2d: torch.Tensor, opacities: torch.Tensor,
                        features: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width: int,
                        height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Front-to-back alpha compositing of per-surfel features.

    Inputs are the projected visible surfels (see `raster_projection`); returns (sum_i w_i f_i [H, W, F],
    alpha = sum_i w_i [H, W]) with w_i = alpha_i T_i.
    """
    n_pixels = width * height
    surfel, pixel = _candidate_pairs(uv_planes, means2d, opacities, radii, depths, width, height)
    out_features = features.new_zeros(n_pixels, features.shape[1])
    out_alpha = opacities.new_zeros(n_pixels)
    if surfel.shape[0] > 0:
        centres = torch.stack([pixel % width, pixel // width], dim=-1).to(uv_planes.dtype) + 0.5
        alpha, _ = surfel_alpha(uv_planes[surfel], means2d[surfel], opacities[surfel], centres)
        log_keep = torch.log1p(-alpha.to(torch.float64))
        inclusive = torch.cumsum(log_keep, 0)
        first = torch.ones_like(pixel, dtype=torch.bool)
        first[1:] = pixel[1:] != pixel[:-1]
        segment = torch.cumsum(first.to(torch.int64), 0) - 1
        start = (inclusive - log_keep)[first]  # exclusive sum at each pixel's first entry
        inclusive = inclusive - start[segment]
        exclusive = inclusive - log_keep
        contributes = (inclusive.detach() > math.log(TRANSMITTANCE_MIN)).to(alpha.dtype)
        weights = alpha * torch.exp(exclusive).to(alpha.dtype) * contributes
        out_features = out_features.index_add(0, pixel, weights[:, None] * features[surfel])
        out_alpha = out_alpha.index_add(0, pixel, weights)
    return out_features.reshape(height, width, -1), out_alpha.reshape(height, width)
