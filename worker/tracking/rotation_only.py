"""Camera motion from point tracks when too few of them measure map points: a turn faster than new points can be
triangulated (a phone swung round, a car's curve on a far scene).

A rotation about the camera centre moves every image point by the same homography K R K^-1, whatever its depth, so
the tracks give the rotation alone (`fit_rotation`: two-point RANSAC on unit bearings, then the least-squares
rotation of the inliers). Tracks that disagree with it reveal translation (parallax): when too many disagree the
frame is not a rotation and is left to the usual loss handling. The few map points still tracked give the camera
position with the rotation held (`position_given_rotation`); with too few of them the position is held.
"""

from __future__ import annotations

import numpy as np


def bearings(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit viewing rays [N, 3] (camera frame) of pixels uv [N, 2] (project convention: centres at +0.5, as K)."""
    rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def rotation_between(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rotation R [3, 3] minimising sum w |target - R source|^2 over unit vectors [N, 3] (Kabsch)."""
    w = np.ones(len(source)) if weights is None else weights
    H = (source * w[:, None]).T @ target
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def angular_errors(source: np.ndarray, target: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Angle (radians) between each target ray and its source ray turned by R."""
    cos = np.clip(np.einsum("ij,ij->i", source @ R.T, target), -1.0, 1.0)
    return np.arccos(cos)


def fit_rotation(source: np.ndarray, target: np.ndarray, tolerance_rad: float, iterations: int = 64,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """The rotation R with target ~ R source (unit rays [N, 3] of the same points in two cameras with one centre)
    agreed by the most rays within `tolerance_rad`, refined on them, and its inlier mask; None for fewer than 3
    rays. Deterministic (seeded samples)."""
    n = len(source)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    best: np.ndarray | None = None
    for _ in range(iterations):
        pair = rng.choice(n, 2, replace=False)
        if np.linalg.norm(np.cross(source[pair[0]], source[pair[1]])) < 1e-3:  # parallel rays fix no rotation
            continue
        inlier = angular_errors(source, target, rotation_between(source[pair], target[pair])) < tolerance_rad
        if best is None or inlier.sum() > best.sum():
            best = inlier
    if best is None or best.sum() < 3:
        return None
    for _ in range(2):  # refit on the inliers, then take the inliers of the refit
        R = rotation_between(source[best], target[best])
        best = angular_errors(source, target, R) < tolerance_rad
        if best.sum() < 3:
            return None
    return rotation_between(source[best], target[best]), best


def position_given_rotation(rotation: np.ndarray, points: np.ndarray, rays: np.ndarray, tolerance_rad: float
                            ) -> tuple[np.ndarray, np.ndarray] | None:
    """Camera centre c (world) that makes the world points [N, 3] lie along the camera rays [N, 3] of a camera with
    camera-to-world `rotation`, and the inlier mask (angle within `tolerance_rad`); None when the points do not
    fix it (fewer than 3, or degenerate). Linear: each point gives [r]_x R^T (X - c) = 0, solved twice (the second
    time on the inliers of the first)."""
    if len(points) < 3:
        return None
    world_rays = rays @ rotation.T  # the rays turned into the world frame
    keep = np.ones(len(points), bool)
    centre = None
    for _ in range(2):
        if keep.sum() < 3:
            return None
        # [d]_x (X - c) = 0  ->  [d]_x c = [d]_x X, stacked over the points
        d, X = world_rays[keep], points[keep]
        skew = np.zeros((len(d), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -d[:, 2], d[:, 1], -d[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = d[:, 2], -d[:, 1], d[:, 0]
        A = skew.reshape(-1, 3)
        b = np.einsum("nij,nj->ni", skew, X).reshape(-1)
        if np.linalg.cond(A) > 1e6:
            return None
        centre = np.linalg.lstsq(A, b, rcond=None)[0]
        towards = points - centre
        norm = np.linalg.norm(towards, axis=1)
        cos = np.einsum("ij,ij->i", towards, world_rays) / np.maximum(norm, 1e-12)
        keep = (np.arccos(np.clip(cos, -1.0, 1.0)) < tolerance_rad) & (norm > 1e-9)
    if centre is None or not np.all(np.isfinite(centre)):
        return None
    return centre, keep
