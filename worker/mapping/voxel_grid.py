"""World voxels of the surfel map: the per-voxel cap that keeps a revisited area from growing the map.

A keyframe's new surfels are counted per world voxel against the map's surfels already in that voxel. A keyframe
that offers a voxel clearly more surfels than the map has there (more than `finer` times as many: a closer view, or
a voxel earlier views saw only in part) tops it up to `min(offered, cap)`; otherwise it adds nothing there. A room
seen again and again from similar distances keeps the size of its first visit, while a closer view still adds
detail, never beyond `cap` surfels a voxel.

Voxels are hashed, not stored: a surfel's voxel is `floor(mean / size)` packed into one int64 key (21 bits per axis,
about 2 million voxels along each axis around the origin), so the cost of a count is that of sorting the keys of the
surfels involved (the new keyframe's and the map's surfels in its view), never the map's extent.
"""

from __future__ import annotations

import torch

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def voxel_keys(means: torch.Tensor, size: float) -> torch.Tensor:
    """[N] int64 key of the voxel of side `size` each of `means` [N, 3] falls in (coordinates beyond +-2^20 voxels
    wrap: far-apart voxels may share a key, which only makes the cap stricter there)."""
    if size <= 0:
        raise ValueError(f"voxel size must be > 0, got {size}")
    ijk = torch.floor(means.detach().to(torch.float64) / size).to(torch.int64) + _OFFSET
    ijk = ijk & _MASK
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


def capped_mask(present: torch.Tensor, offered: torch.Tensor, candidates: torch.Tensor, cap: int,
                finer: float = 1.0) -> torch.Tensor:
    """[M] bool over the offered surfels: those a voxel cap lets into the map.

    present: [N] voxel keys of the map's surfels that can share a voxel with the new ones (those in the view);
    offered: [M] voxel keys of all the new keyframe's surfels (its density per voxel); candidates: [M] bool, the new
    surfels fusion would add (where the map covers the view too little). In each voxel where offered > finer x
    present, the first `min(offered, cap) - present` candidates (in their order) are kept; none elsewhere.
    """
    if cap < 1:
        raise ValueError(f"the voxel cap must be >= 1, got {cap}")
    if offered.shape != candidates.shape:
        raise ValueError("offered and candidates must have the same length")
    keep = torch.zeros(len(offered), dtype=torch.bool, device=offered.device)
    if not bool(candidates.any()):
        return keep
    voxels, inverse = torch.unique(torch.cat([present, offered]), return_inverse=True)
    n_present = torch.bincount(inverse[: len(present)], minlength=len(voxels))
    inv_offered = inverse[len(present):]
    n_offered = torch.bincount(inv_offered, minlength=len(voxels))
    room = torch.where(n_offered > finer * n_present, n_offered.clamp_max(cap) - n_present, 0).clamp_min(0)
    rows = torch.nonzero(candidates, as_tuple=True)[0]
    voxel_of = inv_offered[rows]
    order = torch.argsort(voxel_of, stable=True)
    sorted_voxels = voxel_of[order]
    rank = torch.arange(len(rows), device=rows.device) - torch.searchsorted(sorted_voxels, sorted_voxels)
    keep[rows[order[rank < room[sorted_voxels]]]] = True
    return keep
