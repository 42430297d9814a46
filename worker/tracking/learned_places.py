"""XFeat matching of a frame to remembered keyframes (places), for the jobs where optical flow and ORB fail: wide
baselines, relocalisation against older keyframes and joining a restarted map to an older one.

A place keeps its image; its XFeat descriptor map is computed the first time the place is a candidate (the network
costs several tracked frames, so nothing is extracted while tracking goes well) and cached by frame index. The
place's descriptors are sampled at its keypoints on map points and matched to the frame's XFeat keypoints by mutual
nearest neighbours and verified by PnP + RANSAC and the robust refinement
(`pnp_pose`). The best place by inliers wins.

The network runs on the tracking thread, so its work per frame is bounded: at most `passes_per_frame` network passes
(the frame's own, once per frame, and the maps of places not described yet; a candidate whose map did not fit is
described on a later frame) on `threads` torch threads (one: see `xfeat.torch_threads`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from .pose_optimization import pnp_pose
from .relocalization import Place, Relocalisation
from .xfeat import DescriptorMap, XFeatExtractor, XFeatures, mutual_matches, torch_threads

T = TypeVar("T")


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
    """XFeat on demand (the network loads at the first use) with a cache of the places' descriptor maps and a budget
    of network passes per frame (see the module docstring)."""

    def __init__(self, top_k: int, min_similarity: float, chi2_px: float, min_inliers: int,
                 passes_per_frame: int = 3, threads: int = 1) -> None:
        self.top_k, self.min_similarity = top_k, min_similarity
        self.chi2_px, self.min_inliers = chi2_px, min_inliers
        self.passes_per_frame, self.threads = passes_per_frame, threads
        self._extractor: XFeatExtractor | None = None
        self._cache: dict[int, DescriptorMap] = {}
        self._at_keypoints: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # place -> (keypoints, descriptors)
        self._frame: tuple[int, XFeatures, DescriptorMap] | None = None  # the current frame's pass
        self._budget_frame, self._left = -1, passes_per_frame
        self.passes, self.seconds = 0, 0.0  # network passes so far and their time (what the matcher costs)
        self.most_in_a_frame = 0  # the most passes one frame ran

    @property
    def extractor(self) -> XFeatExtractor:
        if self._extractor is None:  # loaded the first time a frame needs it
            self._extractor = XFeatExtractor(top_k=self.top_k)
        return self._extractor

    def begin_frame(self, index: int) -> None:
        """Frame `index` is being tracked: its budget of network passes starts (once per frame)."""
        if index != self._budget_frame:
            self._budget_frame, self._left = index, self.passes_per_frame

    @property
    def passes_left(self) -> int:
        """Network passes the current frame may still run."""
        return self._left

    def _network(self, work: Callable[[XFeatExtractor], T]) -> T | None:
        """One network pass within the frame's budget (None: the budget is spent), timed and counted."""
        if self._left <= 0:
            return None
        self._left -= 1
        start = time.perf_counter()
        with torch_threads(self.threads):
            out = work(self.extractor)
        self.passes += 1
        self.seconds += time.perf_counter() - start
        self.most_in_a_frame = max(self.most_in_a_frame, self.passes_per_frame - self._left)
        return out

    def describe_image(self, gray: np.ndarray) -> XFeatures | None:
        """XFeat keypoints and descriptors of another image than the frame's (one pass; None: no pass left)."""
        return self._network(lambda xfeat: xfeat.extract(gray))

    def of_frame(self, index: int, gray: np.ndarray, corners: np.ndarray | None = None) -> XFeatures | None:
        """XFeat keypoints and descriptors of frame `index` (its grey image; one pass per frame, kept for the rest of
        the frame), followed by descriptors of the given pixels [M, 2] (e.g. the corners a keyframe tracks: the kind
        of pixel a place is described at); None: the frame's budget is spent."""
        if self._frame is None or self._frame[0] != index:
            found = self._network(lambda xfeat: xfeat.extract_with_map(gray))
            if found is None:
                return None
            self._frame = (index, *found)
        _, found, dense = self._frame
        if corners is None or len(corners) == 0:
            return found
        corners = np.asarray(corners, np.float32).reshape(-1, 2)
        with torch_threads(self.threads):
            at_corners = dense.describe(corners)
        return XFeatures(np.concatenate([found.keypoints, corners]),
                         np.concatenate([found.descriptors, at_corners]),
                         np.concatenate([found.scores, np.zeros(len(corners), np.float32)]))

    def described(self, place: Place) -> bool:
        """Whether the place's descriptor map is cached (matching it costs no network pass)."""
        return place.index in self._cache

    def of_place(self, place: Place) -> DescriptorMap | None:
        """The place image's XFeat descriptor map (cached; None: the place kept no image, or it is not described
        yet and this frame has no pass left)."""
        if place.gray is None or place.gray.size == 0:
            return None
        if place.index not in self._cache:
            found = self._network(lambda xfeat: xfeat.dense_map(place.gray))
            if found is None:
                return None
            self._cache[place.index] = found
        return self._cache[place.index]

    def forget(self, keep: set[int]) -> None:
        """Drop the cached maps of places other than `keep` (frame indices)."""
        for index in [i for i in self._cache if i not in keep]:
            del self._cache[index]
            self._at_keypoints.pop(index, None)

    def matches(self, place: Place, frame: XFeatures) -> tuple[np.ndarray, np.ndarray]:
        """The place's map points [n, 3] matched to keypoints of the frame (indices [n] into `frame`): the
        place's descriptors are sampled at its own keypoints, on the points."""
        descriptors = self._place_descriptors(place)
        if descriptors is None or len(place.points) == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        ia, ib = mutual_matches(descriptors, frame.descriptors, self.min_similarity)
        return place.points[ia], ib

    def _place_descriptors(self, place: Place) -> np.ndarray | None:
        """XFeat descriptors [n, 64] at the place's keypoints (kept while its keypoints stay those: a keyframe
        still in the map gains points)."""
        kept = self._at_keypoints.get(place.index)
        if kept is not None and np.array_equal(kept[0], place.keypoints):
            return kept[1]
        found = self.of_place(place)
        if found is None:
            return None
        with torch_threads(self.threads):
            descriptors = found.describe(place.keypoints)
        self._at_keypoints[place.index] = (place.keypoints.copy(), descriptors)
        return descriptors

    def relocalise(self, frame: XFeatures, places: list[Place], K: np.ndarray, min_inliers: int | None = None
                   ) -> Relocalisation | None:
        """The best verified camera-to-world pose of the frame among `places` (None: none has `min_inliers`, by
        default the matcher's); `keypoints` index the frame's XFeat keypoints. Places not described yet take the
        frame's passes left in the given order; those left over wait for a later frame."""
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
