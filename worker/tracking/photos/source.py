"""Photo registration as a pose source: each frame a photo registered by `IncrementalRegistration`, every
registered photo a keyframe. A photo that cannot be registered is reported lost and holds the last pose; when a
later photo places it (the other side of a gap in an orbit), a `relocalized` event carries its pose (method
`registered later`) and the engine revises the trajectory."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.events import Initialized, Initializing, Relocalized, TrackingLost
from worker.geometry import Intrinsics

from ..base import TrackingResult
from ..projection import camera_matrix, sparse_depth_image
from .config import PhotoRegistrationConfig
from .features import extract_features
from .incremental import IncrementalRegistration, Registration
from .snapshot import load_registration, registration_state

LATE = "registered later"


class PhotoRegistration:
    """PoseSource for photo captures (see the module docstring). Needs the camera's intrinsics."""

    name = "photos"
    keeps_every_frame = True  # a live stream skips no photo: each one is a view no other frame repeats

    def __init__(self, config: PhotoRegistrationConfig | None = None) -> None:
        self.config = config or PhotoRegistrationConfig()
        self.registration: IncrementalRegistration | None = None
        self.last_pose = np.eye(4)
        self.lost = False
        self.waiting_reason = ""

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        if intrinsics is None:
            raise ValueError("photo registration needs the camera's intrinsics (session or frame)")
        if self.registration is None:
            self.registration = IncrementalRegistration(camera_matrix(intrinsics), self.config)
        grey = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY) if frame.image.ndim == 3 else frame.image
        done = self.registration.add(frame.index, extract_features(grey, self.config.max_features))
        if done.state == "waiting":
            return self._waiting(frame.index, done)
        if done.pose is None:
            events = [] if self.lost else [TrackingLost(frame=frame.index, reason=done.reason)]
            self.lost = True
            return TrackingResult(self.last_pose.copy(), tracked=False, keyframe_hint=False, events=events,
                                  quality=0.0)
        events = self._events(frame.index, done)
        self.last_pose, self.lost = done.pose.copy(), False
        quality = min(1.0, done.inliers / max(4.0 * self.config.min_inliers, 1.0))
        return TrackingResult(done.pose.copy(), keyframe_hint=True, depth=self._sparse_depth(frame.index, intrinsics),
                              events=events, quality=quality)

    def _waiting(self, index: int, done: Registration) -> TrackingResult:
        """A photo while no pair has made the first map: the first photo's pose, a placeholder."""
        events = []
        if not self.waiting_reason:
            events.append(Initializing(frame=index, state="waiting_for_parallax", reason=done.reason))
        self.waiting_reason = done.reason or "waiting"
        return TrackingResult(np.eye(4), tracked=True, keyframe_hint=False, events=events, quality=0.0)

    def _events(self, index: int, done: Registration) -> list:
        """`initialized` with the photos that waited; `relocalized` back from a loss, with the photos placed late."""
        frames = [[i, pose.tolist()] for i, pose in sorted(done.posed.items())]
        if done.state == "initialized":
            return [Initialized(frame=index, frames=frames, map=1, points=len(self.registration.map.points),
                                model="essential")]
        if self.lost or frames:
            return [Relocalized(frame=index, method=LATE if frames else "photo registration",
                                inliers=done.inliers, lost_frames=len(frames) or None, frames=frames or None)]
        return []

    def _sparse_depth(self, index: int, camera: Intrinsics) -> np.ndarray:
        """z-depth of photo `index`'s points at their keypoints, 0 elsewhere."""
        m = self.registration.map
        photo = next(p for p in reversed(m.photos) if p.index == index)
        has = np.flatnonzero(photo.point_of >= 0)
        return sparse_depth_image(m.points[photo.point_of[has]], photo.features.keypoints[has], photo.pose, camera)

    def refined_poses(self) -> dict[int, np.ndarray]:
        """Every registered photo's pose after a bundle adjustment of all of them (frame index -> camera-to-world):
        the session's finish moves its keyframes there (worker.pipeline.finish)."""
        if self.registration is None or not self.registration.started:
            return {}
        self.registration.adjust_all()
        return {p.index: p.pose.copy() for p in self.registration.map.photos}

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """Nothing to do: every registered photo is already in the reconstruction."""

    def state_dict(self) -> dict[str, Any]:
        return {"last_pose": self.last_pose, "lost": self.lost, "waiting_reason": self.waiting_reason,
                "registration": None if self.registration is None else registration_state(self.registration)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.last_pose = np.asarray(state["last_pose"], np.float64).reshape(4, 4)
        self.lost, self.waiting_reason = bool(state["lost"]), str(state["waiting_reason"])
        saved = state.get("registration")
        self.registration = None if saved is None else load_registration(saved, self.config)
