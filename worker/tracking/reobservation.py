"""Map points seen again: a keyframe's ORB features matched to the local map's points that no track follows any more
(ORB-SLAM's search by projection), so that a keyframe observes the points of older keyframes that saw the same place
and the covisibility window of bundle adjustment reaches them.

A point gets the descriptor of the ORB keypoint nearest to where a keyframe observed it (within a pixel tolerance
that grows with the keypoint's pyramid level); points without one (all-zero descriptor) are not searched.
"""

from __future__ import annotations

import numpy as np

from .features import Features
from .matching import match_by_projection
from .projection import project


def nearest_keypoints(uv: np.ndarray, orb: Features, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For pixels uv [N, 2]: the index of the nearest ORB keypoint and whether it lies within `radius` [len(orb)]
    pixels (each keypoint's tolerance)."""
    if len(uv) == 0 or len(orb) == 0:
        return np.zeros(len(uv), np.int64), np.zeros(len(uv), bool)
    dx = uv[:, None, 0] - orb.keypoints[None, :, 0]
    dy = uv[:, None, 1] - orb.keypoints[None, :, 1]
    d2 = dx * dx + dy * dy
    nearest = d2.argmin(axis=1)
    return nearest, d2[np.arange(len(uv)), nearest] <= radius[nearest] ** 2


def search_by_projection(positions: np.ndarray, descriptors: np.ndarray, candidates: np.ndarray, pose: np.ndarray,
                         K: np.ndarray, size: tuple[int, int], orb: Features, radius_px: float, max_hamming: int,
                         ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """The candidate points (rows into positions [P, 3] / descriptors [P, 32]) that project into the image of a
    camera at `pose` (width, height = size) next to an ORB keypoint of `orb` whose descriptor matches theirs:
    (rows, keypoint indices), one keypoint per point at the most."""
    if len(candidates) == 0 or len(orb) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    uv, z = project(positions[candidates], pose, K)
    width, height = size
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    rows, uv = candidates[inside], uv[inside]
    found = match_by_projection(uv, descriptors[rows], np.full(len(rows), radius_px), orb, max_hamming, ratio)
    ok = found >= 0
    return rows[ok], found[ok]
