"""Dense refinement of a loop edge between two RGB-D keyframes: projective point-to-plane ICP on their depth.

The ORB + PnP edge is only as good as the depth sampled at a few keypoints (often on depth edges); aligning the
whole depth maps makes it millimetre-accurate when the overlap is real, and a poor final fit rejects it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from worker.geometry import make_sim3, so3_exp
from worker.pipeline.surfel_init import depth_normals


@dataclass
class IcpResult:
    """The refined pose of frame j in frame i (T_i^-1 T_j), the fraction of j's points that found a close
    neighbour in i, and the RMS point-to-plane residual of those (pose units)."""

    relative: torch.Tensor
    inlier_fraction: float
    rms: float


def refine_relative_pose(points_i: torch.Tensor, points_j: torch.Tensor, K: torch.Tensor, relative: torch.Tensor,
                         iterations: int = 15, max_distance: float = 0.05) -> IcpResult:
    """Point-to-plane ICP of j's camera-frame points [H,W,3] onto i's, starting from `relative` (4x4, SE(3)); points
    farther than `max_distance` (pose units) from their match are not paired."""
    H, W = points_i.shape[:2]
    normals_i = depth_normals(points_i.float()).double()
    target = points_i.double()
    valid_j = points_j[..., 2] > 0
    src = points_j.double()[valid_j]
    T = relative.double().clone()
    K = K.double()
    inliers = torch.zeros(0, dtype=torch.bool)
    residual = torch.zeros(0, dtype=torch.float64)
    for _ in range(iterations):
        p = src @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2].clamp_min(1e-6)
        u = torch.floor(K[0, 0] * p[:, 0] / z + K[0, 2]).long()
        v = torch.floor(K[1, 1] * p[:, 1] / z + K[1, 2]).long()
        inside = (p[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        q = torch.zeros_like(p)
        n = torch.zeros_like(p)
        q[inside] = target[v[inside], u[inside]]
        n[inside] = normals_i[v[inside], u[inside]]
        residual = ((p - q) * n).sum(-1)
        inliers = inside & (q[:, 2] > 0) & ((p - q).norm(dim=-1) < max_distance)
        if int(inliers.sum()) < 100:
            break
        pi, ni, ri = p[inliers], n[inliers], residual[inliers]
        J = torch.cat([torch.linalg.cross(pi, ni, dim=-1), ni], dim=-1)  # d r / d (omega, t)
        delta = torch.linalg.solve(J.T @ J + 1e-9 * torch.eye(6, dtype=J.dtype), -J.T @ ri)
        T = make_sim3(so3_exp(delta[:3]), delta[3:]) @ T
        if float(delta.norm()) < 1e-6:
            break
    count = max(1, int(valid_j.sum()))
    rms = float(residual[inliers].pow(2).mean().sqrt()) if bool(inliers.any()) else float("inf")
    return IcpResult(T, float(inliers.sum()) / count, rms)
