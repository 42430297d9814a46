"""XFeat matching of a frame to remembered keyframes (places), for the jobs where optical flow and ORB fail: wide
baselines, relocalisation against older keyframes and joining a restarted map to an older one.

A place keeps its image; its XFeat descriptor map is computed the first time the place is a candidate (the network
costs several tracked frames, so nothing is extracted while tracking goes well) and cached by frame index. The
place's descriptors are sampled at its keypoints on map points and matched to the frame's XFeat keypoints by mutual
nearest neighbours and verified by PnP + RANSAC and the robust refinement
(`pnp_pose`). The best place by inliers wins.
"""

from __future__ import annotations

import time

import numpy as np

from .pose_optimization import pnp_pose
from .relocalization import Place, Relocalisation
from .xfeat import DescriptorMap, XFeatExtractor, XFeatures, mutual_matches


def nearest_within(queries: np.ndarray, targets: np.ndarray, radius: float | np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(rows of `queries` [N, 2], their nearest row of `targets` [M, 2]) for the queries within `radius` pixels
    (one radius, or one per query [N])."""
    if len(queries) == 0 or len(targets) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    dx = queries[:, None, 0] - targets[None, :, 0]
    dy = queries[:, None, 1] - targets[None, :, 1]
    d2 = dx * dx + dy * dy
    nearest = d2.argmin(axis=1)
    near = np.flatnonzero(d2[np.arange(len(queries)), nearest] <= np.square(radius))
    return near, nearest[near]


class LearnedPlaces:
    """XFeat on demand (the network loads at the first use) with a cache of the places' keypoints."""

    def __init__(self, top_k: int, min_similarity: float, chi2_px: float, min_inliers: int) -> None:
        self.top_k, self.min_similarity = top_k, min_similarity
        self.chi2_px, self.min_inliers = chi2_px, min_inliers
        self._extractor: XFeatExtractor | None = None
        self._cache: dict[int, DescriptorMap] = {}
        self.passes, self.seconds = 0, 0.0  # network passes so far and their time (what the matcher costs)

    @property
    def extractor(self) -> XFeatExtractor:
        if self._extractor is None:  # loaded the first time a frame needs it
            self._extractor = XFeatExtractor(top_k=self.top_k)
        return self._extractor

    def extract(self, gray: np.ndarray, corners: np.ndarray | None = None) -> XFeatures:
        """XFeat keypoints and descriptors of a grey image, followed by descriptors of the given pixels [M, 2]
        (e.g. the corners a keyframe tracks: the kind of pixel a place is described at)."""
        start = time.perf_counter()
        found, dense = self.extractor.extract_with_map(gray)
        self._count(start)
        if corners is None or len(corners) == 0:
            return found
        corners = np.asarray(corners, np.float32).reshape(-1, 2)
        return XFeatures(np.concatenate([found.keypoints, corners]),
                         np.concatenate([found.descriptors, dense.describe(corners)]),
                         np.concatenate([found.scores, np.zeros(len(corners), np.float32)]))

    def of_place(self, place: Place) -> DescriptorMap | None:
        """The place image's XFeat descriptor map (cached; None: the place kept no image)."""
        if place.gray is None or place.gray.size == 0:
            return None
        if place.index not in self._cache:
            start = time.perf_counter()
            self._cache[place.index] = self.extractor.dense_map(place.gray)
            self._count(start)
        return self._cache[place.index]

    def _count(self, start: float) -> None:
        self.passes += 1
        self.seconds += time.perf_counter() - start

    def forget(self, keep: set[int]) -> None:
        """Drop the cached maps of places other than `keep` (frame indices)."""
        for index in [i for i in self._cache if i not in keep]:
            del self._cache[index]

    def matches(self, place: Place, frame: XFeatures) -> tuple[np.ndarray, np.ndarray]:
        """The place's map points [n, 3] matched to keypoints of the frame (indices [n] into `frame`): the
        place's descriptors are sampled at its own keypoints, on the points."""
        found = self.of_place(place)
        if found is None or len(place.points) == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        ia, ib = mutual_matches(found.describe(place.keypoints), frame.descriptors, self.min_similarity)
        return place.points[ia], ib

    def relocalise(self, frame: XFeatures, places: list[Place], K: np.ndarray, min_inliers: int | None = None
                   ) -> Relocalisation | None:
        """The best verified camera-to-world pose of the frame among `places` (None: none has `min_inliers`, by
        default the matcher's); `keypoints` index the frame's XFeat keypoints."""
        needed = self.min_inliers if min_inliers is None else min_inliers
        best: Relocalisation | None = None
        for place in places:
            points, keypoints = self.matches(place, frame)
            if len(points) < needed:
                continue
            uv = frame.keypoints[keypoints].astype(np.float64)
            found = pnp_pose(points, uv, K, np.full(len(points), 2.0), self.chi2_px, needed)
            if found is None:
                continue
            pose, inlier = found
            if best is None or inlier.sum() > len(best.keypoints):
                best = Relocalisation(pose, place.index, keypoints[inlier], points[inlier])
        return best
