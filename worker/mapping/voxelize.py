"""Adaptive voxelization of a keyframe's per-pixel surfels (paper eq. 15-16).

The [H, W] grid of surfels is cut into 2x2 blocks. A block whose valid surfels span a small depth range is merged
into one surfel: means, opacities, colours and scales are averaged, quaternions are sign-aligned to the block's
first valid quaternion, summed and renormalised. Blocks whose depth range exceeds tau_d keep their surfels as they
are. Invalid pixels (masked, low confidence, depth <= 0) never contribute.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from worker.geometry import quat_align_sign, quat_normalize

from .surfels import Surfels


@dataclass
class VoxelizedSurfels:
    """Result of `voxelize`: the surfels, the source pixel (row, col) of each, and whether it is a merged block.

    For a merged surfel `pixels` holds the top-left pixel of its 2x2 block.
    """

    surfels: Surfels
    pixels: torch.Tensor  # [N, 2] int64 (row, col)
    merged: torch.Tensor  # [N] bool


def _check_grid(means, quats, scales, opacities, colors) -> tuple[int, int]:
    if means.ndim != 3 or means.shape[-1] != 3:
        raise ValueError(f"means must be [H, W, 3], got {tuple(means.shape)}")
    H, W = means.shape[:2]
    for name, t, tail in (("quats", quats, (4,)), ("scales", scales, (2,)), ("opacities", opacities, ()),
                          ("colors", colors, (3,))):
        if tuple(t.shape) != (H, W, *tail):
            raise ValueError(f"{name} must be {(H, W, *tail)}, got {tuple(t.shape)}")
    return H, W


def valid_pixel_mask(
    means: torch.Tensor, conf: torch.Tensor | None = None, conf_threshold: float = 0.0, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Pixels whose surfel is usable: finite, in front of the camera, confident enough and not masked out."""
    valid = torch.isfinite(means).all(-1) & (means[..., 2] > 0)
    if conf is not None:
        valid &= conf > conf_threshold
    if mask is not None:
        valid &= mask.to(torch.bool)
    return valid


def voxelize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    valid: torch.Tensor | None = None,
    tau_d: float = 0.05,
    relative: bool = True,
    keyframe_id: int = -1,
    merged_scale_factor: float = 1.0,
) -> VoxelizedSurfels:
    """Merge 2x2 blocks of camera-frame per-pixel surfels whose depth range is at most tau_d.

    means [H,W,3] (camera frame; depth = z), quats [H,W,4] wxyz, scales [H,W,2], opacities [H,W], colors [H,W,3];
    valid [H,W] bool (default: z > 0 and finite). With `relative`, the block's depth range is compared with
    tau_d * (mean block depth), which suits monocular maps of arbitrary scale; otherwise with tau_d itself.
    `merged_scale_factor` multiplies the averaged scales of merged surfels (1.0 = the paper's plain average).
    Pixels in a last odd row/column form no block and are kept individually. Output order: merged blocks in raster
    order, then the kept individual surfels in raster order.
    """
    H, W = _check_grid(means, quats, scales, opacities, colors)
    if tau_d < 0:
        raise ValueError(f"tau_d must be >= 0, got {tau_d}")
    base_valid = valid_pixel_mask(means)
    valid = base_valid if valid is None else (valid.to(torch.bool) & base_valid)
    if tuple(valid.shape) != (H, W):
        raise ValueError(f"valid must be [H, W] = {(H, W)}, got {tuple(valid.shape)}")

    device = means.device
    rows = torch.arange(H, device=device)[:, None].expand(H, W)
    cols = torch.arange(W, device=device)[None, :].expand(H, W)
    Hb, Wb = H // 2, W // 2

    def blocks(t: torch.Tensor) -> torch.Tensor:
        """[H, W, ...] -> [Hb, Wb, 4, ...] with the block's pixels in raster order (top-left first)."""
        t = t[: 2 * Hb, : 2 * Wb]
        t = t.reshape(Hb, 2, Wb, 2, *t.shape[2:]).transpose(1, 2)
        return t.reshape(Hb, Wb, 4, *t.shape[4:])

    bv = blocks(valid)
    count = bv.sum(-1)
    z = blocks(means[..., 2])
    z_max = torch.where(bv, z, torch.full_like(z, -torch.inf)).amax(-1)
    z_min = torch.where(bv, z, torch.full_like(z, torch.inf)).amin(-1)
    w = bv.to(means.dtype)
    denom = count.clamp_min(1).to(means.dtype)
    z_mean = (z * w).sum(-1) / denom
    limit = tau_d * z_mean if relative else torch.full_like(z_mean, tau_d)
    merge = (count > 0) & ((z_max - z_min) <= limit)

    def average(t: torch.Tensor) -> torch.Tensor:
        tb = blocks(t)
        wt = w.reshape(*w.shape, *([1] * (tb.ndim - w.ndim)))
        return (tb * wt).sum(2) / denom.reshape(*denom.shape, *([1] * (tb.ndim - 3)))

    qb = blocks(quats)
    first = torch.argmax(bv.to(torch.int8), dim=-1)  # first valid pixel of each block
    reference = torch.gather(qb, 2, first[..., None, None].expand(Hb, Wb, 1, 4))
    q_sum = (quat_align_sign(qb, reference) * w[..., None]).sum(2)

    m = merge
    merged = Surfels(
        means=average(means)[m],
        quats=quat_normalize(q_sum[m]),
        scales=average(scales)[m] * merged_scale_factor,
        opacities=average(opacities)[m],
        colors=average(colors)[m],
        keyframe_ids=torch.full((int(m.sum()),), keyframe_id, dtype=torch.int64, device=device),
    )
    merged_pixels = torch.stack([blocks(rows)[..., 0][m], blocks(cols)[..., 0][m]], dim=-1)

    # Pixels kept individually: valid ones in unmerged blocks or outside the block grid.
    in_merged_block = torch.zeros(H, W, dtype=torch.bool, device=device)
    in_merged_block[: 2 * Hb, : 2 * Wb] = m.repeat_interleave(2, 0).repeat_interleave(2, 1)
    keep = valid & ~in_merged_block
    single = Surfels(
        means=means[keep], quats=quat_normalize(quats[keep]), scales=scales[keep], opacities=opacities[keep],
        colors=colors[keep],
        keyframe_ids=torch.full((int(keep.sum()),), keyframe_id, dtype=torch.int64, device=device),
    )
    single_pixels = torch.stack([rows[keep], cols[keep]], dim=-1)
    return VoxelizedSurfels(
        surfels=Surfels.concat([merged, single]),
        pixels=torch.cat([merged_pixels, single_pixels]),
        merged=torch.cat([torch.ones(len(merged), dtype=torch.bool, device=device),
                          torch.zeros(len(single), dtype=torch.bool, device=device)]),
    )
