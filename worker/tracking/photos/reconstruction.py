"""The growing reconstruction of a photo capture: registered photos, 3D points and which keypoint sees which point."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..bundle_adjustment import Observations
from .features import PhotoFeatures


@dataclass
class RegisteredPhoto:
    """A photo with its pose (camera-to-world) and, per keypoint, the point it observes (-1: none)."""

    index: int
    features: PhotoFeatures
    pose: np.ndarray
    point_of: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.point_of = np.full(len(self.features), -1, np.int64)


class Reconstruction:
    """Photos (slots in registration order), points [P, 3] and observations (slot, keypoint, point)."""

    def __init__(self) -> None:
        self.photos: list[RegisteredPhoto] = []
        self.points = np.zeros((0, 3))
        self._slot: list[int] = []
        self._keypoint: list[int] = []
        self._point: list[int] = []

    def add_photo(self, photo: RegisteredPhoto) -> int:
        """Register a photo; returns its slot."""
        self.photos.append(photo)
        return len(self.photos) - 1

    def add_points(self, positions: np.ndarray) -> np.ndarray:
        """New points; returns their ids."""
        first = len(self.points)
        self.points = np.vstack([self.points, positions.reshape(-1, 3)])
        return np.arange(first, len(self.points))

    def observe(self, slot: int, keypoints: np.ndarray, points: np.ndarray) -> None:
        """Photo `slot`'s keypoints see these points (keypoints that already see one are skipped)."""
        photo = self.photos[slot]
        free = photo.point_of[keypoints] < 0
        keypoints, points = keypoints[free], points[free]
        keypoints, first = np.unique(keypoints, return_index=True)
        points = points[first]
        photo.point_of[keypoints] = points
        self._slot += [slot] * len(keypoints)
        self._keypoint += keypoints.tolist()
        self._point += points.tolist()

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(slot, keypoint, point) of every observation, as arrays."""
        return (np.asarray(self._slot, np.int64), np.asarray(self._keypoint, np.int64),
                np.asarray(self._point, np.int64))

    def observations_of(self, slots: np.ndarray) -> tuple[Observations, np.ndarray]:
        """The bundle-adjustment observations of the points the photos `slots` see, by every photo that sees them,
        and the index of each in `observations()`."""
        slot, keypoint, point = self.observations()
        seen = np.zeros(len(self.points), bool)
        seen[point[np.isin(slot, slots)]] = True
        use = np.flatnonzero(seen[point])
        uv = np.stack([self.photos[s].features.keypoints[k] for s, k in zip(slot[use], keypoint[use])]) \
            if len(use) else np.zeros((0, 2))
        return Observations(slot[use], point[use], uv, np.ones(len(use))), use

    def forget(self, which: np.ndarray) -> None:
        """Drop the observations at these indices of `observations()` (the keypoints see no point after)."""
        if len(which) == 0:
            return
        slot, keypoint, point = self.observations()
        for s, k in zip(slot[which], keypoint[which]):
            self.photos[s].point_of[k] = -1
        keep = np.ones(len(slot), bool)
        keep[which] = False
        self._slot, self._keypoint, self._point = (slot[keep].tolist(), keypoint[keep].tolist(),
                                                   point[keep].tolist())

    def poses(self) -> np.ndarray:
        """Camera-to-world poses [F, 4, 4] in slot order."""
        return np.stack([p.pose for p in self.photos])

    def shared_points(self, slot: int) -> np.ndarray:
        """Per photo slot, how many points it shares with photo `slot`."""
        mine = self.photos[slot].point_of
        mine = np.unique(mine[mine >= 0])
        return np.array([np.isin(p.point_of, mine).sum() for p in self.photos])
