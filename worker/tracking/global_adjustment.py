"""The final bundle adjustment of visual odometry: every archived keyframe and point at once, after the points a
revisit sees again are joined to the first visit's.

Optical flow follows a point only while it stays in view, so a place seen again gets new points, triangulated at
the scale and position the odometry has drifted to; the windowed adjustments never see both. Here each keyframe's
ORB features on map points are matched to those of older keyframes near it that it shares no window with (ratio
test, then the keyframe's own pose refined on the older keyframe's points: only matches the geometry agrees with
are kept), matched points become one, and one bundle adjustment moves all keyframes but the two oldest (they hold
pose and scale). This is ORB-SLAM's loop fusion and global bundle adjustment, run once, at the end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from .bundle_adjustment import Observations, bundle_adjust, reprojection_chi2
from .keyframe_archive import ArchivedKeyframe, KeyframeArchive
from .vo_config import VisualOdometryConfig

RATIO = 0.8  # Lowe's ratio of the matches between two keyframes' ORB features
HELD = 2  # the oldest keyframes held still: pose and scale


@dataclass
class GlobalAdjustment:
    """Its outcome: adjusted poses by frame index (empty when it did not run), the revisit pairs verified, the
    points joined, the observations used and the seconds it took; `local_scales`, once the keyframes' moves were
    made: the spread of the scales their parts of the map took (worker.tracking.keyframe_scale.scale_spread)."""

    poses: dict[int, np.ndarray]
    pairs: int
    joined: int
    observations: int
    seconds: float
    local_scales: tuple[float, float, float] | None = None


class _Roots:
    """Union-find over point ids: the oldest id of a joined set stands for it."""

    def __init__(self) -> None:
        self.parent: dict[int, int] = {}

    def find(self, x: int) -> int:
        root = x
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        while x != root:  # path compression
            self.parent[x], x = root, self.parent.get(x, x)
        return root

    def join(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.parent[max(ra, rb)] = min(ra, rb)
        return True


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _candidates(keyframes: list[ArchivedKeyframe], n: int, scene_depth: float, c: VisualOdometryConfig
                ) -> list[int]:
    """The older keyframes keyframe `n` may see again: not in its window, near in position and direction."""
    pose = keyframes[n].pose
    near = []
    for m in range(n - c.fuse_min_gap + 1):
        other = keyframes[m].pose
        distance = float(np.linalg.norm(other[:3, 3] - pose[:3, 3])) / scene_depth
        angle = _rotation_deg(pose, other)
        if distance <= c.fuse_max_distance and angle <= c.fuse_max_angle_deg:
            near.append((distance + angle / c.fuse_max_angle_deg * c.fuse_max_distance, m))
    return [m for _, m in sorted(near)[:c.fuse_candidates]]


def _verified_matches(older: ArchivedKeyframe, newer: ArchivedKeyframe, positions: dict[int, np.ndarray],
                      K: np.ndarray, matcher: cv2.BFMatcher, c: VisualOdometryConfig
                      ) -> list[tuple[int, int]]:
    """(older point id, newer point id) of the ORB matches that place `newer` on `older`'s points."""
    if len(older.orb_descriptors) < c.fuse_min_inliers or len(newer.orb_descriptors) < c.fuse_min_inliers:
        return []
    pairs = matcher.knnMatch(older.orb_descriptors, newer.orb_descriptors, k=2)
    good = [m[0] for m in pairs
            if len(m) == 2 and m[0].distance < RATIO * m[1].distance and m[0].distance <= c.max_hamming]
    if len(good) < c.fuse_min_inliers:
        return []
    qa = np.array([m.queryIdx for m in good])
    qb = np.array([m.trainIdx for m in good])
    world = np.array([positions[int(i)] for i in older.orb_point_ids[qa]], np.float64)
    w2c = np.linalg.inv(newer.pose)
    # matches far from where the keyframe's own pose puts their points are wrong, or the pair is (drift moves
    # points by less): they leave before the pose is refined on the rest
    camera = world @ w2c[:3, :3].T + w2c[:3, 3]
    projected = camera[:, :2] / np.maximum(camera[:, 2:3], 1e-9) * K[[0, 1], [0, 1]] + K[:2, 2]
    radius = c.fuse_search_share * 2.0 * max(K[0, 2], K[1, 2])
    near = (camera[:, 2] > 0) & (np.linalg.norm(projected - newer.orb_keypoints[qb], axis=1) <= radius)
    if near.sum() < c.fuse_min_inliers:
        return []
    qa, qb, world = qa[near], qb[near], world[near]
    # the keyframe's pose, refined on the matches while the tolerance narrows (it starts near: no RANSAC needed)
    rvec, tvec = cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3].reshape(3, 1).copy()
    pixels = newer.orb_keypoints[qb].astype(np.float64)
    inliers = np.ones(len(qa), bool)
    for tolerance in (radius / 2.0, radius / 4.0, 4.0 * c.fuse_pnp_px, 2.0 * c.fuse_pnp_px, c.fuse_pnp_px):
        rvec, tvec = cv2.solvePnPRefineLM(world[inliers], pixels[inliers], K, None, rvec, tvec)
        reprojected = cv2.projectPoints(world, rvec, tvec, K, None)[0].reshape(-1, 2)
        inliers = np.linalg.norm(reprojected - pixels, axis=1) <= max(tolerance, c.fuse_pnp_px)
        if inliers.sum() < c.fuse_min_inliers:
            return []
    inliers = np.flatnonzero(inliers)
    return list(zip(older.orb_point_ids[qa[inliers]].tolist(), newer.orb_point_ids[qb[inliers]].tolist(),
                    strict=True))


def _observations(keyframes: list[ArchivedKeyframe], roots: _Roots, positions: dict[int, np.ndarray],
                  sigma_of) -> tuple[Observations, np.ndarray]:
    """Every keyframe's observations of the joined points (one per point and keyframe) and the points' starting
    positions (each joined set at its oldest point's)."""
    rows: dict[int, int] = {}
    slots, points, uv, sigma = [], [], [], []
    for n, kf in enumerate(keyframes):
        seen: set[int] = set()
        for pid, pixel, octave in zip(kf.point_ids.tolist(), kf.uv, kf.octaves, strict=True):
            root = roots.find(pid)
            if root in seen or root not in positions:
                continue
            seen.add(root)
            row = rows.setdefault(root, len(rows))
            slots.append(n)
            points.append(row)
            uv.append(pixel)
            sigma.append(octave)
    start = np.array([positions[r] for r in rows], np.float64).reshape(-1, 3)
    obs = Observations(np.array(slots, np.int64), np.array(points, np.int64),
                       np.array(uv, np.float64).reshape(-1, 2), sigma_of(np.array(sigma, np.int64)))
    return obs, start


def adjust_globally(archive: KeyframeArchive, K: np.ndarray, scene_depth: float, c: VisualOdometryConfig,
                    sigma_of) -> GlobalAdjustment:
    """The final bundle adjustment of the archive's keyframes (see the module docstring); `sigma_of` maps octaves
    to pixel sigmas. No poses when the archive mixes maps or too few revisits were verified."""
    started = time.perf_counter()
    keyframes = archive.ordered()
    if archive.mixed_maps or len(keyframes) <= HELD:
        return GlobalAdjustment({}, 0, 0, 0, time.perf_counter() - started)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    roots, pairs, joined = _Roots(), 0, 0
    for n in range(len(keyframes)):
        for m in _candidates(keyframes, n, scene_depth, c):
            matches = _verified_matches(keyframes[m], keyframes[n], archive.positions, K, matcher, c)
            pairs += bool(matches)
            joined += sum(roots.join(a, b) for a, b in matches)
    if pairs < c.fuse_min_pairs:
        return GlobalAdjustment({}, pairs, joined, 0, time.perf_counter() - started)
    obs, points = _observations(keyframes, roots, archive.positions, sigma_of)
    poses = np.stack([kf.pose for kf in keyframes])
    fixed = np.arange(len(keyframes)) < HELD
    for _ in range(c.final_adjustment_rounds):
        poses, points, solved = bundle_adjust(poses, fixed, points, obs, K, c.final_adjustment_iterations,
                                              c.huber_sigmas)
        if not solved:
            return GlobalAdjustment({}, pairs, joined, len(obs.point), time.perf_counter() - started)
        # gross outliers (wrongly joined points, bad tracks) leave before the next round
        keep = reprojection_chi2(poses, points, obs, K) <= 4 * c.chi2_px
        obs = Observations(obs.keyframe[keep], obs.point[keep], obs.uv[keep], obs.sigma[keep])
    adjusted = {kf.index: pose for kf, pose in zip(keyframes, poses, strict=True)}
    return GlobalAdjustment(adjusted, pairs, joined, len(obs.point), time.perf_counter() - started)
