"""Where a frame is in a stored map: keyframe retrieval by place words, ORB matches to the keyframe's 3D points,
PnP + RANSAC, a robust pose refinement and, where the frame has depth, a check that the map's points lie where the
frame's depth sees them.

A stored map's keyframes (`MapView`: pose, camera, grey image, depth) become places once (ORB corners with a depth,
lifted into the map's world); `MapLocalizer.locate` then finds a frame among them (worker.tracking.relocalization's
place recognizer, as relocalisation after a loss does) and returns a `MapFix` with its quality, or None. It never
returns a pose it could not verify: too few inliers, a large reprojection error or depth that disagrees all give
None, so an unrelated scene stays unlocated.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worker.loop.descriptors import default_vocabulary
from worker.loop.vocabulary import Vocabulary
from worker.tracking.dense_alignment import PyramidLevel, align, build_pyramid
from worker.tracking.features import OrbExtractor
from worker.tracking.relocalization import Place, PlaceRecognizer
from worker.tracking.vo_config import VisualOdometryConfig


@dataclass
class MapView:
    """A keyframe of a stored map: id, camera-to-world pose (a similarity in an up-to-scale map), camera matrix,
    grey image uint8 [H, W] (or its JPEG, decoded when first needed) and depth [h, w] in the keyframe's units (any
    resolution; 0 or NaN: none); `place` when the map was packaged with it (`describe_view`)."""

    id: int
    pose: np.ndarray
    K: np.ndarray
    gray: np.ndarray | None
    depth: np.ndarray | None
    jpeg: bytes | None = None
    place: Place | None = None

    def image(self) -> np.ndarray:
        """The grey image (decoded from the JPEG once)."""
        if self.gray is None:
            if self.jpeg is None:
                raise ValueError(f"map view {self.id} has no image")
            self.gray = cv2.imdecode(np.frombuffer(self.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
            if self.gray is None:
                raise ValueError(f"map view {self.id}: the image does not decode")
        return self.gray


@dataclass(frozen=True)
class LocalizerSettings:
    """How sure a fix must be. `min_inliers` PnP inliers (and this share of the matches tried), at most
    `max_reprojection_px` RMS over them; with the frame's depth, at least `min_depth_agreement` of the inliers that
    have one within `depth_tolerance` (relative) of the depth the map predicts."""

    min_inliers: int = 40
    min_inlier_share: float = 0.3
    max_reprojection_px: float = 2.0
    min_depth_agreement: float = 0.6
    depth_tolerance: float = 0.05
    candidates: int = 5
    refine_with_depth: bool = True  # RGB-D frames in a metric map: dense alignment to the keyframe found
    min_overlap: float = 0.5  # ... accepted where this share of the keyframe's surface meets the frame's
    max_refinement_move: float = 0.05  # ... and it moves the PnP pose less than this (of the scene's depth)


@dataclass
class MapFix:
    """A verified pose of a frame in the map's world (rigid camera-to-world, the map's units) and its quality."""

    pose: np.ndarray
    view: int
    inliers: int
    matches: int
    reprojection_px: float
    depth_agreement: float | None

    def quality(self) -> dict[str, float | int | None]:
        """The fix's quality as plain numbers (for messages and records)."""
        return {"keyframe": int(self.view), "inliers": int(self.inliers), "matches": int(self.matches),
                "reprojection_px": round(float(self.reprojection_px), 3),
                "depth_agreement": None if self.depth_agreement is None else round(float(self.depth_agreement), 3)}


class MapLocalizer:
    """Finds frames in a stored map's keyframes (see the module docstring)."""

    def __init__(self, views: list[MapView], settings: LocalizerSettings | None = None) -> None:
        self.settings = settings or LocalizerSettings()
        self.vo_config = VisualOdometryConfig(reloc_candidates=self.settings.candidates,
                                              reloc_min_inliers=max(10, self.settings.min_inliers))
        self.extractor = OrbExtractor(self.vo_config)
        self.recognizer = PlaceRecognizer(self.vo_config)
        self.places = [p for p in (v.place or describe_view(v, self.extractor, self.recognizer.vocabulary,
                                                             self.settings.min_inliers) for v in views)
                       if p is not None]
        self._views = {int(v.id): v for v in views}
        self._pyramids: dict[int, list[PyramidLevel]] = {}

    def __len__(self) -> int:
        return len(self.places)

    def add_place(self, place: Place) -> None:
        """Look frames up among `place` too (a place another session shared; no image to refine against)."""
        if place.bag is None:
            place.bag = self.recognizer.vocabulary.bag_of_words(place.descriptors)
        self.places = [*self.places, place]  # a new list: a lookup in another thread keeps the one it has

    def locate(self, gray: np.ndarray, K: np.ndarray, depth: np.ndarray | None = None) -> MapFix | None:
        """The frame's verified pose in the map, or None (see `LocalizerSettings` for what verified means).
        `gray` uint8 [H, W], `K` its camera matrix, `depth` the frame's own depth at its resolution (optional)."""
        if not self.places:
            return None
        features = self.extractor.extract(gray)
        if len(features) < self.settings.min_inliers:
            return None
        K = np.asarray(K, np.float64)
        sigma = self.extractor.level_sigmas(features.octaves)
        found = self.recognizer.relocalise(features, self.places, K, sigma)
        if found is None:
            return None
        uv = features.keypoints[found.keypoints].astype(np.float64)
        error = _reprojection_rms(found.pose, found.points, uv, K)
        agreement = None if depth is None else _depth_agreement(found.pose, found.points, uv, depth,
                                                                 self.settings.depth_tolerance)
        fix = MapFix(found.pose, found.place, len(found.keypoints), found.matches, error, agreement)
        if not self._verified(fix):
            return None
        if depth is not None and self.settings.refine_with_depth:
            fix.pose = self._refined(fix, gray, depth, K)
        return fix

    def _refined(self, fix: MapFix, gray: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
        """The fix's pose refined by dense RGB-D alignment of the frame to the keyframe it was found from
        (photometric and point-to-plane), or the PnP pose where the alignment does not clearly hold."""
        view = self._views.get(fix.view)
        if view is None or view.depth is None or abs(np.linalg.det(view.pose[:3, :3]) - 1.0) > 1e-6:
            return fix.pose  # an up-to-scale map's keyframe: its depth is not in the frame's units
        reference = self._pyramids.get(fix.view)
        if reference is None:
            reference = self._pyramids[fix.view] = _pyramid(view.image(), view.depth, view.K)
        current = _pyramid(gray, depth, K)
        start = np.linalg.inv(fix.pose) @ view.pose  # T_cur_ref
        result = align(reference, current, start)
        if not result.ok or result.overlap < self.settings.min_overlap:
            return fix.pose
        refined = view.pose @ np.linalg.inv(result.T)
        scene = float(np.median(view.depth[view.depth > 0])) if np.any(view.depth > 0) else 1.0
        if np.linalg.norm(refined[:3, 3] - fix.pose[:3, 3]) > self.settings.max_refinement_move * scene:
            return fix.pose
        return refined

    def _verified(self, fix: MapFix) -> bool:
        s = self.settings
        if fix.inliers < s.min_inliers or fix.inliers < s.min_inlier_share * max(fix.matches, 1):
            return False
        if not np.isfinite(fix.reprojection_px) or fix.reprojection_px > s.max_reprojection_px:
            return False
        return fix.depth_agreement is None or fix.depth_agreement >= s.min_depth_agreement


def describe_view(view: MapView, extractor: OrbExtractor | None = None, vocabulary: Vocabulary | None = None,
                  min_points: int = LocalizerSettings.min_inliers) -> Place | None:
    """The view as a place to relocalize against: its ORB corners that have a depth, lifted into the map's world,
    and their bag of words; None with fewer than `min_points` of them (or no depth)."""
    if view.depth is None:
        return None
    extractor = extractor or OrbExtractor(VisualOdometryConfig())
    gray = view.image()
    features = extractor.extract(gray)
    height, width = gray.shape
    depth = np.nan_to_num(np.asarray(view.depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if depth.shape != (height, width):
        depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
    cols = np.clip(features.keypoints[:, 0].astype(np.int64), 0, width - 1)
    rows = np.clip(features.keypoints[:, 1].astype(np.int64), 0, height - 1)
    z = depth[rows, cols].astype(np.float64)
    keep = z > 0
    if keep.sum() < min_points:
        return None
    uv1 = np.column_stack([features.keypoints[keep].astype(np.float64), np.ones(int(keep.sum()))])
    camera_points = (np.linalg.inv(np.asarray(view.K, np.float64)) @ uv1.T).T * z[keep, None]
    pose = np.asarray(view.pose, np.float64)
    world = camera_points @ pose[:3, :3].T + pose[:3, 3]
    place = Place(int(view.id), pose, features.keypoints[keep], features.descriptors[keep], world)
    place.bag = (vocabulary or default_vocabulary()).bag_of_words(place.descriptors)
    return place


def place_arrays(place: Place) -> dict[str, np.ndarray]:
    """A place as the map package keeps it (protocol.map_package: a keyframe's `places`)."""
    return {"keypoints": np.asarray(place.keypoints, np.float32), "descriptors": np.asarray(place.descriptors,
                                                                                            np.uint8),
            "points": np.asarray(place.points, np.float64), "bag": np.asarray(place.bag, np.float32)}


def place_from_arrays(view_id: int, pose: np.ndarray, arrays: dict[str, np.ndarray]) -> Place:
    """The place a map package kept for keyframe `view_id` (see `place_arrays`)."""
    place = Place(int(view_id), np.asarray(pose, np.float64), np.asarray(arrays["keypoints"], np.float32),
                  np.asarray(arrays["descriptors"], np.uint8), np.asarray(arrays["points"], np.float64))
    place.bag = np.asarray(arrays["bag"], np.float32)
    return place


def _pyramid(gray: np.ndarray, depth: np.ndarray, K: np.ndarray) -> list[PyramidLevel]:
    """Dense-alignment levels of a grey image and its depth (brought to the image's size), 3 levels."""
    height, width = gray.shape
    depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if depth.shape != (height, width):
        depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
    return build_pyramid(gray.astype(np.float32) / 255.0, depth, np.asarray(K, np.float64), levels=3)


def _camera_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World points [n, 3] in the camera of rigid camera-to-world `pose`."""
    R, t = pose[:3, :3], pose[:3, 3]
    return (points - t) @ R


def _reprojection_rms(pose: np.ndarray, points: np.ndarray, uv: np.ndarray, K: np.ndarray) -> float:
    cam = _camera_points(pose, points)
    if np.any(cam[:, 2] <= 0):
        return float("inf")
    projected = (cam / cam[:, 2:3]) @ K.T
    return float(np.sqrt(np.mean(np.sum((projected[:, :2] - uv) ** 2, axis=1))))


def _depth_agreement(pose: np.ndarray, points: np.ndarray, uv: np.ndarray, depth: np.ndarray,
                     tolerance: float) -> float | None:
    """The share of inliers whose frame depth lies within `tolerance` (relative) of the map's prediction, among
    those with a depth; None when fewer than ten have one (nothing to judge by)."""
    height, width = depth.shape
    cols = np.clip(uv[:, 0].astype(np.int64), 0, width - 1)
    rows = np.clip(uv[:, 1].astype(np.int64), 0, height - 1)
    seen = np.nan_to_num(np.asarray(depth, np.float64)[rows, cols], nan=0.0)
    predicted = _camera_points(pose, points)[:, 2]
    valid = seen > 0
    if valid.sum() < 10:
        return None
    return float(np.mean(np.abs(seen[valid] - predicted[valid]) <= tolerance * predicted[valid]))
