"""Joining a restarted map to an older one: the similarity (scale included) that brings the new map into the old
map's frame, measured where a keyframe of the new map recognises a place of the old one.

A map restarted after a loss (two views anchored at the last tracked frame) has the old map's pose but only an
estimate of its scale. When one of its keyframes is relocalised against a remembered keyframe of an older map (ORB
words, then PnP + RANSAC and a robust refinement on the place's 3D points), the same pixels measure a point of each
map: the recovered pose gives the rotation and position, and the ratio of their depths the scale. The result is a
Sim(3) edge between the two maps (`MapLink`), which visual odometry applies to its map and hands to the pose graph.
Where ORB finds no place (wide baselines), XFeat matches give the same hit (`link_from_hit`).

Similarities are 4x4 matrices [s R, t; 0, 1]; poses stay rigid camera-to-world matrices whose positions carry the
map's units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .features import Features
from .projection import to_camera
from .relocalization import Place, PlaceRecognizer, Relocalisation


def similarity(rotation: np.ndarray, translation: np.ndarray, scale: float) -> np.ndarray:
    """The 4x4 similarity x -> scale * rotation @ x + translation."""
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = scale * rotation, translation
    return out


def similarity_scale(S: np.ndarray) -> float:
    """The scale of a 4x4 similarity."""
    return float(np.cbrt(np.linalg.det(S[:3, :3])))


def similarity_inverse(S: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 similarity."""
    s = similarity_scale(S)
    R = S[:3, :3] / s
    return similarity(R.T, -R.T @ S[:3, 3] / s, 1.0 / s)


def moved_pose(S: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """A rigid camera-to-world pose moved by the similarity S (rotation turned, position scaled and moved)."""
    s = similarity_scale(S)
    out = np.eye(4)
    out[:3, :3] = (S[:3, :3] / s) @ pose[:3, :3]
    out[:3, 3] = S[:3, :3] @ pose[:3, 3] + S[:3, 3]
    return out


def moved_points(S: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points [N, 3] moved by the similarity S."""
    return points @ S[:3, :3].T + S[:3, 3]


@dataclass
class MapLink:
    """A keyframe of the new map recognised a place of an older map: `transform` (new map -> old map, 4x4
    similarity), its scale, the place, the 3D-3D pairs that measured it and the spread of their depth ratios
    (median absolute deviation of the log ratio)."""

    place: Place
    transform: np.ndarray
    scale: float
    pairs: int
    spread: float


def link_maps(recognizer: PlaceRecognizer, features: Features, points: np.ndarray, pose: np.ndarray,
              places: list[Place], K: np.ndarray, sigma: np.ndarray, min_inliers: int, min_pairs: int,
              max_spread: float) -> MapLink | None:
    """The similarity from the new map to the old one (None: no place found, too few pairs, or depth ratios that
    disagree by more than `max_spread` in log scale).

    features: a keyframe's keypoints; points [n, 3]: the new map's point each keypoint lies on (NaN: none); pose: the
    keyframe's camera-to-world pose in the new map; places: keyframes of older maps; sigma: each keypoint's pixel
    sigma; min_inliers: PnP inliers needed; min_pairs: of which on the new map's points."""
    on_points = np.isfinite(points).all(axis=1)
    if on_points.sum() < min_pairs or not places:
        return None
    hit = recognizer.relocalise(features, places, K, sigma)
    if hit is None or len(hit.keypoints) < min_inliers:
        return None
    return link_from_hit(hit, points, pose, places, min_pairs, max_spread)


def link_from_hit(hit: Relocalisation, points: np.ndarray, pose: np.ndarray, places: list[Place], min_pairs: int,
                  max_spread: float) -> MapLink | None:
    """The similarity from the new map to the old one measured by a keyframe's verified match to an older place
    (`hit`: its pose in the old map, the inlier keypoints and their old points), whichever features found it:
    points [n, 3] are the new map's point each of the keyframe's keypoints lies on (NaN: none), pose its pose in
    the new map (None: too few pairs, or depth ratios that disagree by more than `max_spread` in log scale)."""
    on_points = np.isfinite(points).all(axis=1)
    shared = on_points[hit.keypoints]  # the place's points this keyframe also has in its own map
    depth_old = to_camera(hit.points[shared], hit.pose)[:, 2]
    depth_new = to_camera(points[hit.keypoints[shared]], pose)[:, 2]
    valid = (depth_old > 0) & (depth_new > 0)
    if valid.sum() < min_pairs:
        return None
    log_ratio = np.log(depth_old[valid] / depth_new[valid])
    log_scale = float(np.median(log_ratio))
    spread = float(np.median(np.abs(log_ratio - log_scale)))
    if spread > max_spread:
        return None
    scale = float(np.exp(log_scale))
    # The keyframe's camera lands on the recovered pose: R = R_old R_new^T, t = p_old - s R p_new.
    R = hit.pose[:3, :3] @ pose[:3, :3].T
    transform = similarity(R, hit.pose[:3, 3] - scale * R @ pose[:3, 3], scale)
    place = next(p for p in places if p.index == hit.place)
    return MapLink(place, transform, scale, int(valid.sum()), spread)
