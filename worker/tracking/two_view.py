"""Two-view initialisation of a monocular map: essential matrix (RANSAC, five points), the pose it implies, and
triangulated points, accepted only with enough parallax; the scale makes the points' median depth 1."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .features import Features
from .matching import ratio_matches
from .projection import invert_pose
from .triangulation import good_points, parallax_cos, triangulate
from .vo_config import VisualOdometryConfig


@dataclass
class TwoViewMap:
    """Camera b's pose (camera-to-world, camera a at the origin), the keypoints (ia in a, ib in b) of the
    triangulated points [n, 3] (in a's frame) and their median triangulation angle in degrees."""

    pose_b: np.ndarray
    ia: np.ndarray
    ib: np.ndarray
    points: np.ndarray
    parallax_deg: float


@dataclass
class TwoViewAttempt:
    """The outcome of one try: the map (None: not yet), the number of descriptor matches and why it failed."""

    map: TwoViewMap | None
    matches: int
    reason: str = ""


def initialise_two_view(a: Features, b: Features, K: np.ndarray, config: VisualOdometryConfig,
                        sigma_a: np.ndarray, sigma_b: np.ndarray) -> TwoViewAttempt:
    """Try to build a two-view map from features of frames a and b (sigma_a/sigma_b: pixel noise per keypoint)."""
    ia, ib = ratio_matches(a.descriptors, b.descriptors, config.match_ratio, config.max_hamming)
    return two_view_from_matches(a.keypoints[ia], b.keypoints[ib], K, config, sigma_a[ia], sigma_b[ib], ia, ib)


def two_view_from_matches(pa: np.ndarray, pb: np.ndarray, K: np.ndarray, config: VisualOdometryConfig,
                          sigma_a: np.ndarray, sigma_b: np.ndarray, ia: np.ndarray | None = None,
                          ib: np.ndarray | None = None) -> TwoViewAttempt:
    """Try to build a two-view map from matched pixels pa, pb [N, 2] (pixel noise sigma_a, sigma_b [N]); the map's
    ia, ib are `ia`, `ib` [N] (default: 0..N-1) at the matches it triangulated."""
    n = len(pa)
    ia = np.arange(n) if ia is None else ia
    ib = np.arange(n) if ib is None else ib
    attempt = _attempt(pa.astype(np.float64), pb.astype(np.float64), ia, ib, K, config, sigma_a, sigma_b)
    return TwoViewAttempt(attempt, n) if isinstance(attempt, TwoViewMap) else TwoViewAttempt(None, n, attempt)


def _attempt(pa, pb, ia, ib, K, config, sigma_a, sigma_b) -> TwoViewMap | str:
    if len(ia) < config.init_min_matches:
        return f"{len(ia)} matches < {config.init_min_matches}"
    E, mask = cv2.findEssentialMat(pa, pb, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or mask is None or E.shape[0] < 3:
        return "no essential matrix"
    best: TwoViewMap | None = None
    for n in range(E.shape[0] // 3):  # the five-point solver may return several candidates
        candidate = _triangulate_candidate(E[3 * n: 3 * n + 3], pa, pb, ia, ib, mask.ravel() > 0, K, config,
                                           sigma_a, sigma_b)
        if candidate is not None and (best is None or len(candidate.points) > len(best.points)):
            best = candidate
    if best is None or len(best.points) < config.init_min_points:
        return f"{0 if best is None else len(best.points)} points triangulated < {config.init_min_points}"
    if best.parallax_deg < config.init_min_parallax_deg:
        return f"median parallax {best.parallax_deg:.2f} deg < {config.init_min_parallax_deg}"
    return best


def _triangulate_candidate(E, pa, pb, ia, ib, inlier, K, config, sigma_a, sigma_b) -> TwoViewMap | None:
    count, R, t, _ = cv2.recoverPose(E, pa[inlier], pb[inlier], K)
    if count < config.init_min_points:
        return None
    w2c_b = np.eye(4)
    w2c_b[:3, :3], w2c_b[:3, 3] = R, t.ravel()
    pose_a, pose_b = np.eye(4), invert_pose(w2c_b)
    sel = np.flatnonzero(inlier)
    points = triangulate(pose_a, pose_b, pa[sel], pb[sel], K)
    ok = good_points(points, pose_a, pose_b, pa[sel], pb[sel], sigma_a[sel], sigma_b[sel], K,
                     config.chi2_px, 0.0)
    if ok.sum() < config.init_min_points:
        return None
    points, sel = points[ok], sel[ok]
    # The median angle over all consistent points (not only the wide ones) tells rotation from translation.
    angles = np.rad2deg(np.arccos(np.clip(parallax_cos(points, pose_a, pose_b), -1, 1)))
    parallax = float(np.median(angles))
    wide = angles >= config.min_parallax_deg
    points, sel = points[wide], sel[wide]
    if len(points) < config.init_min_points:
        return None
    scale = 1.0 / float(np.median(points[:, 2]))
    pose_b[:3, 3] *= scale
    return TwoViewMap(pose_b, ia[sel], ib[sel], points * scale, parallax)
