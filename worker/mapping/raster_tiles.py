"""gsplat's 16x16 tile binning rule, in torch (the compiled path repeats the same rule in C++)."""

from __future__ import annotations

import torch

from .raster_projection import TILE_SIZE


def tile_grid(width: int, height: int, tile_size: int = TILE_SIZE) -> tuple[int, int]:
    """Number of tiles (across, down) covering a width x height image."""
    return (width + tile_size - 1) // tile_size, (height + tile_size - 1) // tile_size


def tile_ranges(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int,
                tile_size: int = TILE_SIZE) -> torch.Tensor:
    """Per-surfel tile rectangle [M, 4] int64 (x0, y0, x1, y1), end exclusive.

    gsplat: x from floor((cx - rx) / ts) to ceil((cx + rx) / ts), clamped to the tile grid; likewise y.
    """
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    c = means2d.detach() / tile_size
    r = radii.to(c.dtype) / tile_size
    lo = torch.floor(c - r).to(torch.int64)
    hi = torch.ceil(c + r).to(torch.int64)
    limit = torch.tensor([tiles_x, tiles_y], device=c.device)
    lo = torch.minimum(lo.clamp_min(0), limit)
    hi = torch.minimum(hi.clamp_min(0), limit)
    return torch.cat([lo, hi], dim=-1)


def bin_surfels_to_tiles(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width: int,
                         height: int, tile_size: int = TILE_SIZE) -> tuple[torch.Tensor, torch.Tensor]:
    """(surfel index [P], tile id [P]) of every (surfel, tile) overlap, ordered by tile, then by centre depth.

    Ties in depth keep the surfel order (gsplat sorts stably by tile | depth).
    """
    tiles_x, _ = tile_grid(width, height, tile_size)
    rect = tile_ranges(means2d, radii, width, height, tile_size)
    order = torch.sort(depths.detach(), stable=True).indices
    rect = rect[order]
    nx, ny = rect[:, 2] - rect[:, 0], rect[:, 3] - rect[:, 1]
    counts = (nx * ny).clamp_min(0)
    surfel = torch.repeat_interleave(order, counts)
    rank = torch.arange(int(counts.sum()), device=means2d.device) - torch.repeat_interleave(
        torch.cumsum(counts, 0) - counts, counts)
    nx_rep = torch.repeat_interleave(nx.clamp_min(1), counts)
    rect_rep = torch.repeat_interleave(rect, counts, dim=0)
    tile_x = rect_rep[:, 0] + rank % nx_rep
    tile_y = rect_rep[:, 1] + rank // nx_rep
    tile = tile_y * tiles_x + tile_x
    by_tile = torch.sort(tile, stable=True).indices
    return surfel[by_tile], tile[by_tile]
