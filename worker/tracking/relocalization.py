"""Relocalisation by place recognition: keyframes' bags of ORB words rank the places a lost frame may show, then
descriptor matches to each place's 3D points are verified by PnP + RANSAC and a robust pose refinement."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from worker.loop.descriptors import default_vocabulary
from worker.loop.vocabulary import Vocabulary

from .features import Features
from .matching import ratio_matches
from .pose_optimization import pnp_pose
from .vo_config import VisualOdometryConfig


@dataclass
class Place:
    """A keyframe remembered for relocalisation: frame index, pose, and its keypoints that have a 3D point
    (keypoints [n, 2], descriptors [n, 32], world points [n, 3]); the map it belongs to and the similarity that
    took that map's coordinates to the odometry's output when the keyframe was made (`map_join`); its grey image
    when kept, for learned matching (`learned_places`)."""

    index: int
    pose: np.ndarray
    keypoints: np.ndarray
    descriptors: np.ndarray
    points: np.ndarray
    bag: np.ndarray | None = None
    map_id: int = 0
    output: np.ndarray = field(default_factory=lambda: np.eye(4))
    gray: np.ndarray | None = None

    def to_state(self) -> dict:
        return {"index": self.index, "pose": self.pose, "keypoints": self.keypoints,
                "descriptors": self.descriptors, "points": self.points, "map_id": self.map_id,
                "output": self.output, "gray": np.zeros((0, 0), np.uint8) if self.gray is None else self.gray}

    @classmethod
    def from_state(cls, s: dict) -> Place:
        return cls(int(s["index"]), np.asarray(s["pose"], np.float64).reshape(4, 4),
                   np.asarray(s["keypoints"], np.float32).reshape(-1, 2),
                   np.asarray(s["descriptors"], np.uint8).reshape(-1, 32),
                   np.asarray(s["points"], np.float64).reshape(-1, 3), map_id=int(s.get("map_id", 0)),
                   output=np.asarray(s.get("output", np.eye(4)), np.float64).reshape(4, 4),
                   gray=_image(s.get("gray")))


def _image(value: object) -> np.ndarray | None:
    gray = np.asarray(value if value is not None else np.zeros((0, 0)), np.uint8)
    return np.ascontiguousarray(gray) if gray.size else None


@dataclass
class Relocalisation:
    """A recovered camera-to-world pose, the place it was found from, the PnP inliers (keypoint indices in the
    lost frame and their world points) and how many descriptor matches PnP was given (0: not counted)."""

    pose: np.ndarray
    place: int
    keypoints: np.ndarray
    points: np.ndarray
    matches: int = 0


class PlaceRecognizer:
    """Bag-of-words shortlist + geometric verification over the given places."""

    def __init__(self, config: VisualOdometryConfig, vocabulary: Vocabulary | None = None) -> None:
        self.config = config
        self.vocabulary = vocabulary or default_vocabulary()

    def _bag(self, descriptors: np.ndarray) -> np.ndarray:
        return self.vocabulary.bag_of_words(descriptors)

    def shortlist(self, features: Features, places: list[Place]) -> list[Place]:
        """The places most alike in words, best first."""
        if len(places) <= self.config.reloc_candidates:
            return list(places)
        for place in places:
            if place.bag is None:
                place.bag = self._bag(place.descriptors)
        scores = Vocabulary.score(self._bag(features.descriptors), np.stack([p.bag for p in places]))
        order = np.argsort(-scores, kind="stable")[: self.config.reloc_candidates]
        return [places[n] for n in order]

    def relocalise(self, features: Features, places: list[Place], K: np.ndarray, sigma: np.ndarray
                   ) -> Relocalisation | None:
        """The best verified pose of a frame (features, per-keypoint pixel sigma) among `places`, or None."""
        best: Relocalisation | None = None
        for place in self.shortlist(features, places):
            found = self._verify(features, place, K, sigma)
            if found is not None and (best is None or len(found.keypoints) > len(best.keypoints)):
                best = found
        return best

    def _verify(self, features: Features, place: Place, K: np.ndarray, sigma: np.ndarray) -> Relocalisation | None:
        c = self.config
        ia, ib = ratio_matches(features.descriptors, place.descriptors, 0.9, c.max_hamming)
        if len(ia) < c.reloc_min_inliers:
            return None
        X, uv = place.points[ib], features.keypoints[ia].astype(np.float64)
        found = pnp_pose(X, uv, K, sigma[ia], c.chi2_px, c.reloc_min_inliers)
        if found is None:
            return None
        pose, inlier = found
        return Relocalisation(pose, place.index, ia[inlier], X[inlier], matches=len(ia))
