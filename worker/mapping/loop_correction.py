"""Loop correction of the map (paper sec. 4.3): each keyframe's surfels move rigidly with its pose update."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from worker.geometry import sim3_inverse

from .surfels import Surfels


def pose_deltas(
    old_poses: Mapping[int, torch.Tensor], new_poses: Mapping[int, torch.Tensor]
) -> dict[int, torch.Tensor]:
    """Delta T_new * T_old^-1 (Sim(3), world frame) for every keyframe in `new_poses`."""
    deltas = {}
    for kf_id, T_new in new_poses.items():
        if kf_id not in old_poses:
            raise ValueError(f"pose update for unknown keyframe {kf_id}")
        T_old = old_poses[kf_id]
        if tuple(T_new.shape) != (4, 4) or tuple(T_old.shape) != (4, 4):
            raise ValueError(f"keyframe {kf_id}: poses must be 4x4 matrices")
        T_new = T_new.to(torch.float64)
        deltas[int(kf_id)] = T_new @ sim3_inverse(T_old.to(torch.float64))
    return deltas


def apply_keyframe_deltas(surfels: Surfels, deltas: Mapping[int, torch.Tensor]) -> Surfels:
    """Move every surfel bound to a keyframe in `deltas` by that keyframe's Sim(3) delta; others stay put.

    Computed in float64 and cast back, so the motion is exact to the surfels' precision.
    """
    if not deltas or len(surfels) == 0:
        return surfels
    ids = surfels.keyframe_ids
    affected = torch.zeros(len(surfels), dtype=torch.bool, device=surfels.device)
    per_surfel = torch.eye(4, dtype=torch.float64, device=surfels.device).repeat(len(surfels), 1, 1)
    for kf_id, delta in deltas.items():
        mask = ids == kf_id
        if mask.any():
            per_surfel[mask] = delta.to(device=surfels.device, dtype=torch.float64)
            affected |= mask
    if not affected.any():
        return surfels
    dtype = surfels.means.dtype
    moved = surfels.select(affected).to(dtype=torch.float64).transform_per_surfel(per_surfel[affected]).to(dtype=dtype)
    out = surfels.clone()
    for name, value in moved.tensors().items():
        getattr(out, name)[affected] = value
    return out


def correct_map(
    surfels: Surfels, old_poses: Mapping[int, torch.Tensor], new_poses: Mapping[int, torch.Tensor]
) -> Surfels:
    """Apply a loop closure's optimised keyframe poses to the map (rigid per-keyframe motion)."""
    return apply_keyframe_deltas(surfels, pose_deltas(old_poses, new_poses))
