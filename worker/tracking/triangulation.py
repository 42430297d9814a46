"""Linear triangulation of matched pixels seen from two posed cameras, and the checks a new point must pass."""

from __future__ import annotations

import cv2
import numpy as np

from .projection import invert_pose, project


def triangulate(pose_a: np.ndarray, pose_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray
                ) -> np.ndarray:
    """World points [N, 3] from pixels uv_a, uv_b [N, 2] of cameras posed camera-to-world (DLT; may be inf)."""
    if len(uv_a) == 0:
        return np.zeros((0, 3))
    P_a = K @ invert_pose(pose_a)[:3]
    P_b = K @ invert_pose(pose_b)[:3]
    X = cv2.triangulatePoints(P_a, P_b, uv_a.T.astype(np.float64), uv_b.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (X[:3] / X[3]).T


def parallax_cos(points: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """Cosine of the angle at each point between the rays to the two camera centres."""
    ra = points - pose_a[:3, 3]
    rb = points - pose_b[:3, 3]
    return (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)


def good_points(points: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray,
                sigma_a: np.ndarray, sigma_b: np.ndarray, K: np.ndarray, chi2: float, min_parallax_deg: float
                ) -> np.ndarray:
    """Mask of triangulated points that are finite, in front of both cameras, reproject within chi2 (in pixel
    sigmas squared) in both, and are seen under at least `min_parallax_deg`."""
    ok = np.isfinite(points).all(axis=1)
    safe = np.where(ok[:, None], points, 0.0)
    for pose, uv, sigma in ((pose_a, uv_a, sigma_a), (pose_b, uv_b, sigma_b)):
        proj, z = project(safe, pose, K)
        err2 = ((proj - uv) ** 2).sum(1) / sigma ** 2
        ok &= (z > 0) & (err2 < chi2)
    ok &= parallax_cos(safe, pose_a, pose_b) < np.cos(np.deg2rad(min_parallax_deg))
    return ok

