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

Where no place verifies, `glue_relocalise` is the wide-baseline fallback: XFeat keypoints of both images detected at
twice their size (the network sees detail in 8 x 8 cells: a small object in a 270 x 480 photo has few) are matched
by LighterGlue, and a place verifies when the PnP pose on its map points agrees with the two-view motion of all the
matches. On the instant-ngp fox (photos 30 degrees apart) mutual nearest neighbours give 26-43 chance inliers and
LighterGlue 140-190 true ones; a pair costs several XFeat passes, so it runs only where the above found nothing.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import cv2
import numpy as np

from .pose_optimization import pnp_pose
from .relocalization import Place, Relocalisation
from .xfeat import DescriptorMap, XFeatExtractor, XFeatures, mutual_matches, torch_threads

if TYPE_CHECKING:
    from .xfeat.glue import LighterGlue

T = TypeVar("T")
GLUE_UPSAMPLE = 2  # XFeat runs on the image enlarged this many times for LighterGlue


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
                 passes_per_frame: int = 3, threads: int = 1, glue_keypoints: int = 2048,
                 glue_min_confidence: float = 0.1, glue_candidates: int = 6, glue_point_inliers: int = 12,
                 radius_px: float = 3.0) -> None:
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
        self.glue_keypoints, self.glue_min_confidence, self.radius_px = glue_keypoints, glue_min_confidence, radius_px
        self.glue_candidates, self.glue_point_inliers = glue_candidates, glue_point_inliers
        self._glue_extractor: XFeatExtractor | None = None
        self._glue: LighterGlue | None = None
        self._glue_cache: dict[int, XFeatures] = {}
        self.glue_pairs, self.glue_seconds = 0, 0.0  # LighterGlue pairs matched so far and their time
        self._glue_at: int | None = None  # the frame of the last LighterGlue try

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
        for index in [i for i in self._glue_cache if i not in keep]:
            del self._glue_cache[index]

    def glue_features(self, gray: np.ndarray, corners: np.ndarray | None = None) -> XFeatures:
        """XFeat keypoints of a grey image detected at `GLUE_UPSAMPLE` times its size (`glue_keypoints` of them),
        in the image's own pixels, followed by the given pixels [M, 2] described at that size: LighterGlue's input."""
        if self._glue_extractor is None:
            self._glue_extractor = XFeatExtractor(top_k=self.glue_keypoints)
        start = time.perf_counter()
        height, width = gray.shape[:2]
        enlarged = cv2.resize(gray, (width * GLUE_UPSAMPLE, height * GLUE_UPSAMPLE), interpolation=cv2.INTER_LINEAR)
        with torch_threads(self.threads):  # outside the frame's pass budget: `glue_due` bounds these tries
            found, dense = self._glue_extractor.extract_with_map(enlarged)
            keypoints, descriptors = found.keypoints / GLUE_UPSAMPLE, found.descriptors
            if corners is not None and len(corners):
                corners = np.asarray(corners, np.float32).reshape(-1, 2)
                keypoints = np.concatenate([keypoints, corners])
                descriptors = np.concatenate([descriptors, dense.describe(corners * GLUE_UPSAMPLE)])
        self.passes += 1
        self.seconds += time.perf_counter() - start
        return XFeatures(keypoints.astype(np.float32), descriptors, np.zeros(len(keypoints), np.float32))

    def glue_due(self, index: int, every: int) -> bool:
        """Whether frame `index` may try LighterGlue (and, if so, counts as the last try): at most one try every
        `every` frames, since a try that finds nothing still costs up to `glue_candidates` pairs."""
        if self._glue_at is not None and 0 <= index - self._glue_at < every:
            return False
        self._glue_at = index
        return True

    def glue_relocalise(self, gray: np.ndarray, places: list[Place], K: np.ndarray, min_inliers: int | None = None
                        ) -> tuple[Relocalisation, np.ndarray] | None:
        """The pose of a frame (grey image) from the first of `places` (at most `glue_candidates` are tried) that
        verifies by LighterGlue, and the frame's pixels [n, 2] of its inliers (`keypoints` index them); None: none
        verified. A place verifies when all its matches hold an essential matrix with `min_inliers` inliers and the
        PnP pose on its map points (`glue_point_inliers` of them) agrees with that two-view motion: a place keeps
        few map points (100-150 on the fox), far fewer than the matches that show the views overlap, and on the
        fox wrong places also give 150-170 essential inliers, so the agreement is the test."""
        needed = self.min_inliers if min_inliers is None else min_inliers
        places = [p for p in places if p.gray is not None and p.gray.size and len(p.points) >= self.glue_point_inliers]
        places = places[: self.glue_candidates]
        if not places:
            return None
        if self._glue is None:
            from .xfeat.glue import LighterGlue  # kornia loads only when a frame needs the matcher

            self._glue = LighterGlue(self.glue_min_confidence)
        frame = self.glue_features(gray)
        for place in places:
            found = self._place_glue_features(place)
            start = time.perf_counter()
            with torch_threads(self.threads):
                ia, ib, _ = self._glue.match(found, place.gray.shape[::-1], frame, gray.shape[::-1])
            self.glue_pairs += 1
            self.glue_seconds += time.perf_counter() - start
            motion = two_view_motion(found.keypoints[ia], frame.keypoints[ib], K, needed)
            if motion is None:
                continue
            # The matches on the place's map points: at one of its keypoints, or at a detection near one.
            detected = len(found) - len(place.keypoints)
            on_point = ia >= detected
            near, nearest = nearest_within(found.keypoints[ia[~on_point]], place.keypoints, self.radius_px)
            point = np.concatenate([ia[on_point] - detected, nearest])
            matched = np.concatenate([ib[on_point], ib[~on_point][near]])
            if len(point) < self.glue_point_inliers:
                continue
            X, uv = place.points[point], frame.keypoints[matched].astype(np.float64)
            result = pnp_pose(X, uv, K, np.full(len(X), 2.0), self.chi2_px, self.glue_point_inliers)
            if result is None or not agrees(motion, place.pose, result[0]):
                continue
            pose, inlier = result
            return Relocalisation(pose, place.index, np.flatnonzero(inlier), X[inlier]), uv
        return None

    def _place_glue_features(self, place: Place) -> XFeatures:
        """A place's LighterGlue input (cached): its detections, then its keypoints on map points."""
        if place.index not in self._glue_cache:
            self._glue_cache[place.index] = self.glue_features(place.gray, place.keypoints)
        return self._glue_cache[place.index]

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


@dataclass
class TwoViewMotion:
    """Rotation [3, 3] and unit translation [3] taking points of the first camera to the second (x2 = R x1 + t)."""

    rotation: np.ndarray
    direction: np.ndarray
    inliers: int


def two_view_motion(pa: np.ndarray, pb: np.ndarray, K: np.ndarray, min_inliers: int) -> TwoViewMotion | None:
    """The relative motion of two views from matched pixels [n, 2] by an essential matrix (RANSAC, 1 px) with at
    least `min_inliers` inliers (None: fewer)."""
    if len(pa) < max(min_inliers, 8):
        return None
    pa, pb = pa.astype(np.float64), pb.astype(np.float64)
    E, mask = cv2.findEssentialMat(pa, pb, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or mask is None or int(mask.sum()) < min_inliers:
        return None
    _, R, t, _ = cv2.recoverPose(E[:3], pa, pb, K, mask=mask.copy())
    return TwoViewMotion(R, t.ravel() / max(np.linalg.norm(t), 1e-12), int(mask.sum()))


def agrees(motion: TwoViewMotion, place_pose: np.ndarray, pose: np.ndarray, max_rotation_deg: float = 2.5,
           max_direction_deg: float = 5.0) -> bool:
    """Whether a camera-to-world `pose` found from a place's map points agrees with the two-view motion from the
    place (camera-to-world `place_pose`) to it: the rotations within `max_rotation_deg`, and the directions of travel
    within `max_direction_deg` where the pose moved at all. True poses (fox, ICL pairs 28-37 degrees apart) agree
    within 0.8-2.1 degrees and 0.8-2.0 degrees; a synthetic room's wrong one (3 degrees, 12 cm off) at 3.0 and 8.7."""
    relative = np.linalg.inv(pose) @ place_pose  # place camera -> this camera
    R, t = relative[:3, :3], relative[:3, 3]
    turned = np.degrees(np.arccos(np.clip((np.trace(motion.rotation.T @ R) - 1.0) / 2.0, -1.0, 1.0)))
    if turned > max_rotation_deg:
        return False
    length = np.linalg.norm(t)
    if length < 1e-9:
        return True
    return float(np.degrees(np.arccos(np.clip(motion.direction @ t / length, -1.0, 1.0)))) <= max_direction_deg
