"""Two-view initialisation of a monocular map. Both a homography and an essential matrix are fitted (RANSAC) and
scored by their symmetric transfer error (`model_selection`); the chosen model gives the relative motion
(decomposition + cheirality for a homography, `recoverPose` for an essential matrix), and the triangulated points
are accepted only with enough parallax. Without parallax (a rotation about the optical centre, or too little
translation yet) the attempt fails but keeps the rotation it measured, so the caller can hold the orientation and
wait. The scale makes the points' median depth 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .features import Features
from .matching import ratio_matches
from .model_selection import rotation_of_homography, score_models
from .projection import invert_pose
from .triangulation import good_points, parallax_cos, triangulate
from .vo_config import VisualOdometryConfig

AMBIGUITY = 0.75  # a second motion with this share of the best one's points leaves the choice open (ORB-SLAM's)
MIN_OFF_PLANE = 10  # matches off a homography's plane that decide between its two solutions


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
    """The outcome of one try: the map (None: not yet), the number of matches, why it failed, the model chosen
    ("homography" | "essential" | "" when none could be fitted), the score ratio R_H, and camera b's orientation
    relative to a (camera-to-world rotation, a at the origin) when the model gave one, map or not."""

    map: TwoViewMap | None
    matches: int
    reason: str = ""
    model: str = ""
    score_ratio: float = 0.0
    rotation: np.ndarray | None = None

    @property
    def rotation_only(self) -> bool:
        """No map because the views show no parallax, while the homography explains them: a rotation."""
        return self.map is None and self.model == "homography" and self.rotation is not None


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
    if n < config.init_min_matches:
        return TwoViewAttempt(None, n, f"{n} matches < {config.init_min_matches}")
    pa, pb = pa.astype(np.float64), pb.astype(np.float64)
    H, mask_h = cv2.findHomography(pa, pb, cv2.RANSAC, np.sqrt(config.chi2_px))
    if H is not None and mask_h is not None and mask_h.sum() >= 8:  # refit on every inlier (least squares + LM)
        H = cv2.findHomography(pa[mask_h.ravel() > 0], pb[mask_h.ravel() > 0], 0)[0]
    E, mask_e = cv2.findEssentialMat(pa, pb, K, cv2.RANSAC, 0.999, 1.0)
    # The five-point solver may return several candidates: each is scored, and each one's motion is tried.
    essentials = [E[3 * k: 3 * k + 3] for k in range(E.shape[0] // 3)] if E is not None else []
    F = max((_fundamental(e, K) for e in essentials), key=lambda f: score_models(None, f, pa, pb).fundamental,
            default=None)
    scores = score_models(H, F, pa, pb)
    if H is None and F is None:
        return TwoViewAttempt(None, n, "neither a homography nor an essential matrix fits")
    use_h = H is not None and (F is None or scores.prefers_homography)
    model = "homography" if use_h else "essential"
    if use_h:
        # The decomposition's two physical solutions explain the plane's points equally well; points off the
        # plane (inliers of the epipolar geometry only) tell them apart.
        candidates = _homography_motions(H, K)
        inlier = scores.inliers_h | scores.inliers_f
    else:
        inlier = mask_e.ravel() > 0 if mask_e is not None else scores.inliers_f
        candidates = [motion for e in essentials for motion in _essential_motions(e, pa, pb, K, inlier)]
    tried = [_triangulate_candidate(R, t, pa, pb, ia, ib, inlier, K, config, sigma_a, sigma_b)
             for R, t in candidates]
    # A plane's points fit both physical solutions of its homography alike: the matches off the plane (inliers
    # of the epipolar geometry only) tell them apart when there are enough of them.
    off_plane = np.flatnonzero(scores.inliers_f & ~scores.inliers_h) if use_h else np.zeros(0, np.int64)
    decisive = off_plane if len(off_plane) >= MIN_OFF_PLANE else None

    def support(c: _Candidate) -> int:
        return c.count if decisive is None else int(np.isin(c.good, decisive).sum())

    tried.sort(key=lambda c: (support(c), c.count), reverse=True)
    best = tried[0] if tried else None
    rotation = rotation_of_homography(H, K).T if use_h else (best.rotation.T if best is not None else None)
    out = TwoViewAttempt(None, n, "", model, scores.ratio, rotation)
    if best is None or best.map is None:
        count = 0 if best is None else best.count
        out.reason = f"{count} points triangulated < {config.init_min_points} ({model})"
        return out
    two = best.map
    if two.parallax_deg < config.init_min_parallax_deg:
        out.reason = f"median parallax {two.parallax_deg:.2f} deg < {config.init_min_parallax_deg} ({model})"
        return out
    rival = next((c for c in tried[1:] if _angle_deg(c.rotation @ best.rotation.T) > 0.5), None)
    if rival is not None and support(rival) > AMBIGUITY * support(best):
        # Two motions explain the matches about as well (a plane seen from a short baseline): wait, as ORB-SLAM
        # does, until the motion or the points off the plane tell them apart.
        out.reason = f"ambiguous motion: {support(rival)} vs {support(best)} points ({model})"
        out.rotation = None
        return out
    if len(two.points) < config.init_min_points:
        out.reason = (f"{len(two.points)} points seen under {config.min_parallax_deg} deg or more < "
                      f"{config.init_min_points} ({model})")
        return out
    out.map, out.rotation = two, two.pose_b[:3, :3].copy()
    return out


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def _fundamental(E: np.ndarray, K: np.ndarray) -> np.ndarray:
    K_inv = np.linalg.inv(K)
    return K_inv.T @ E @ K_inv


def _homography_motions(H: np.ndarray, K: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (R_ba, t_ba) solutions of the homography's decomposition (t up to the plane's distance)."""
    count, rotations, translations, _ = cv2.decomposeHomographyMat(H, K)
    return [(rotations[k], translations[k].ravel()) for k in range(count)]


def _essential_motions(E: np.ndarray, pa: np.ndarray, pb: np.ndarray, K: np.ndarray, inlier: np.ndarray
                       ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The motion recoverPose picks by cheirality (points in front of both cameras)."""
    _, R, t, _ = cv2.recoverPose(E, pa[inlier], pb[inlier], K)
    return [(R, t.ravel())]


@dataclass
class _Candidate:
    """One motion (R_ba) tried: its map (None: too few points), the matches consistent with it."""

    map: TwoViewMap | None
    rotation: np.ndarray
    good: np.ndarray  # indices of the matches it triangulates in front of both cameras, reprojecting

    @property
    def count(self) -> int:
        return len(self.good)


def _triangulate_candidate(R, t, pa, pb, ia, ib, inlier, K, config, sigma_a, sigma_b) -> _Candidate:
    """The map of motion (R_ba, t_ba) over the model's inliers. The consistent matches (in front of both
    cameras, reprojecting) judge the candidates, as cheirality does; the map keeps the points seen under
    `min_parallax_deg` or more (perhaps too few: the caller judges)."""
    none = np.zeros(0, np.int64)
    if np.linalg.norm(t) < 1e-9:
        return _Candidate(None, R, none)
    w2c_b = np.eye(4)
    w2c_b[:3, :3], w2c_b[:3, 3] = R, t / np.linalg.norm(t)
    pose_a, pose_b = np.eye(4), invert_pose(w2c_b)
    sel = np.flatnonzero(inlier)
    points = triangulate(pose_a, pose_b, pa[sel], pb[sel], K)
    ok = good_points(points, pose_a, pose_b, pa[sel], pb[sel], sigma_a[sel], sigma_b[sel], K,
                     config.chi2_px, 0.0)
    points, sel = points[ok], sel[ok]
    good = sel.copy()
    if len(good) < config.init_min_points:
        return _Candidate(None, R, good)
    # The median angle over all consistent points (not only the wide ones) tells rotation from translation.
    angles = np.rad2deg(np.arccos(np.clip(parallax_cos(points, pose_a, pose_b), -1, 1)))
    parallax = float(np.median(angles))
    wide = angles >= config.min_parallax_deg
    points, sel = points[wide], sel[wide]
    if len(points) == 0:
        return _Candidate(None, R, good)
    scale = 1.0 / float(np.median(points[:, 2]))
    pose_b[:3, 3] *= scale
    return _Candidate(TwoViewMap(pose_b, ia[sel], ib[sel], points * scale, parallax), R, good)
