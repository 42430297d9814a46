"""Focal length from a predicted camera-frame pointmap (robust Weiszfeld fit, principal point at the centre)."""

from __future__ import annotations

import torch

from worker.geometry import Intrinsics, pixel_grid


def estimate_focal(points_cam: torch.Tensor, conf: torch.Tensor | None = None, iterations: int = 10,
                   min_depth: float = 1e-6) -> float:
    """The focal length f (fx = fy) that best maps points [H, W, 3] onto their pixels, in pixels.

    Minimises sum_i w_i * |uv_i - f * xy_i / z_i| (an L1-type, outlier-robust cost) by Weiszfeld iterations starting
    from the least-squares solution; uv are pixel centres relative to the image centre (W/2, H/2). `conf` [H, W]
    optionally weights the pixels. Points with z <= min_depth are ignored.
    """
    if points_cam.ndim != 3 or points_cam.shape[-1] != 3:
        raise ValueError(f"points_cam must be [H, W, 3], got {tuple(points_cam.shape)}")
    H, W = points_cam.shape[:2]
    if conf is not None and conf.shape != (H, W):
        raise ValueError(f"conf must be [{H}, {W}], got {tuple(conf.shape)}")
    pts = points_cam.detach().to(torch.float64).reshape(-1, 3)
    uv = pixel_grid(W, H, dtype=torch.float64, device=pts.device).reshape(-1, 2)
    uv = uv - torch.tensor([W / 2.0, H / 2.0], dtype=torch.float64, device=pts.device)
    weights = torch.ones(len(pts), dtype=torch.float64, device=pts.device)
    if conf is not None:
        weights = conf.detach().to(torch.float64).reshape(-1)
    valid = (pts[:, 2] > min_depth) & torch.isfinite(pts).all(dim=1) & (weights > 0)
    if int(valid.sum()) < 2:
        raise ValueError("too few points in front of the camera to estimate a focal length")
    xy = pts[valid, :2] / pts[valid, 2:3]
    uv, weights = uv[valid], weights[valid]
    dot = (uv * xy).sum(dim=1)
    sq = (xy * xy).sum(dim=1)
    focal = (weights * dot).sum() / (weights * sq).sum().clamp_min(1e-12)
    for _ in range(iterations):
        residual = (uv - focal * xy).norm(dim=1).clamp_min(1e-8)
        w = weights / residual
        focal = (w * dot).sum() / (w * sq).sum().clamp_min(1e-12)
    focal = float(focal)
    if not focal > 0:
        raise ValueError("the pointmap gives a non-positive focal length (points behind the camera?)")
    return focal


def intrinsics_from_focal(focal: float, width: int, height: int) -> Intrinsics:
    """Pinhole intrinsics with fx = fy = focal and the principal point at the image centre."""
    return Intrinsics(focal, focal, width / 2.0, height / 2.0, width, height)
