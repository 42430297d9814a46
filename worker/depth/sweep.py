"""Plane-sweep geometry: pose checks, the per-view homography terms, inverse-depth hypotheses, window statistics."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def pose_problem(pose: np.ndarray) -> str | None:
    """Why a camera-to-world 4x4 cannot be used (None when it can): non-finite, not affine, or singular."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        return f"pose must be 4x4, got {pose.shape}"
    if not np.all(np.isfinite(pose)):
        return "pose has NaN or infinite entries"
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0]):
        return "pose's last row is not [0, 0, 0, 1]"
    if abs(np.linalg.det(pose[:3, :3])) < 1e-12:
        return "pose's rotation block is singular"
    return None


@dataclass(frozen=True)
class ViewGeometry:
    """Where reference pixels land in one view: homogeneous point A p + w b for inverse depth w (pixel-centre
    coordinates, p = (x + 0.5, y + 0.5, 1)); `baseline` is the camera-centre distance in pose units."""

    A: np.ndarray  # [3, 3] K R K^-1
    b: np.ndarray  # [3] K t
    baseline: float


def view_geometry(K: np.ndarray, ref_pose: np.ndarray, pose: np.ndarray) -> ViewGeometry:
    """The plane-sweep terms of a view at `pose` for the reference camera at `ref_pose` (both camera-to-world;
    similarities are accepted: depth is then in the reference camera's units)."""
    rel = np.linalg.inv(pose) @ ref_pose  # reference camera -> view camera
    K_inv = np.linalg.inv(K)
    return ViewGeometry(A=K @ rel[:3, :3] @ K_inv, b=K @ rel[:3, 3],
                        baseline=float(np.linalg.norm(pose[:3, 3] - ref_pose[:3, 3])))


def inverse_depths(near: float, far: float, count: int) -> np.ndarray:
    """`count` inverse depths from 1/far to 1/near, uniformly spaced (float64)."""
    return np.linspace(1.0 / far, 1.0 / near, count)


# A hypothesis counts towards a view's sweep only where the view sees it at least this fraction of its depth in the
# reference camera: a neighbour ahead of the reference (moving forward) sees the nearest hypotheses behind it, and
# its segments start where the points come into its view, not at the near plane.
MIN_DEPTH_RATIO = 0.5


def sweep_pixels(view: ViewGeometry, width: int, height: int, near: float, far: float) -> float:
    """Median length in pixels of the epipolar segments between depths `far` and `near` of a 5x5 grid of pixels
    over the image, each clipped to the depths the view sees in front of it (`MIN_DEPTH_RATIO`; a segment wholly
    behind the view does not count; 0 if none counts). Not the centre alone: moving forward, the centre is the
    epipole, where no baseline gives parallax."""
    grid = (np.arange(5) + 0.5) / 5.0
    u, v = np.meshgrid(grid * width, grid * height)
    p = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])  # [3, 25]
    rotated = view.A @ p
    # The view's depth over the reference's, for a point at inverse depth w: rotated_z + b_z w (linear in w).
    lo, hi = np.full(p.shape[1], 1.0 / far), np.full(p.shape[1], 1.0 / near)
    bz = float(view.b[2])
    if bz < 0:  # the view is ahead: the ratio falls as points come nearer
        hi = np.minimum(hi, (rotated[2] - MIN_DEPTH_RATIO) / -bz)
    elif bz > 0:
        lo = np.maximum(lo, (MIN_DEPTH_RATIO - rotated[2]) / bz)
    seen = (lo < hi) & (rotated[2] + bz * lo >= MIN_DEPTH_RATIO - 1e-9)
    if not seen.any():
        return 0.0
    far_end = rotated[:, seen] + view.b[:, None] * lo[seen]
    near_end = rotated[:, seen] + view.b[:, None] * hi[seen]
    lengths = np.linalg.norm(near_end[:2] / near_end[2] - far_end[:2] / far_end[2], axis=0)
    return float(np.median(lengths))


def window_sums(values: np.ndarray, radius: int) -> np.ndarray:
    """Sums over (2r+1)^2 windows clipped at the border, float64 [H, W]."""
    out = np.asarray(values, dtype=np.float64)
    for axis in (0, 1):
        n = out.shape[axis]
        cs = np.concatenate([np.zeros_like(np.take(out, [0], axis=axis)), np.cumsum(out, axis=axis)], axis=axis)
        idx = np.arange(n)
        hi, lo = np.minimum(idx + radius, n - 1) + 1, np.maximum(idx - radius, 0)
        out = np.take(cs, hi, axis=axis) - np.take(cs, lo, axis=axis)
    return out


def window_counts(height: int, width: int, radius: int) -> np.ndarray:
    """Pixels in each clipped window, float64 [H, W]."""
    return window_sums(np.ones((height, width)), radius)


def reference_stats(ref: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Window sums of the reference image and of its squared deviations from the window mean (float32 [H, W])."""
    s = window_sums(ref, radius)
    ss = window_sums(np.asarray(ref, dtype=np.float64) ** 2, radius)
    n = window_counts(*ref.shape, radius)
    return s.astype(np.float32), np.maximum(ss - s * s / n, 0.0).astype(np.float32)
