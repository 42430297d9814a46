"""RGB-only sessions with `tracking.source` auto: video or photos, told apart by the time between the first two
frames. Video (frames closer than `tracking.photos.min_interval_s`) goes to visual odometry, whose optical flow
follows small steps; photos go to photo registration (worker.tracking.photos), which matches features however far
apart the views are. The first frame waits for the second (a placeholder pose, as visual odometry gives it), then
both go through the chosen source."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.tracking.base import TrackingResult

VIDEO, PHOTOS = "visual_odometry", "photos"


class MonocularChoice:
    """Visual odometry or photo registration, chosen at the second frame (module docstring). `new_video` and
    `new_photos` build the two sources."""

    def __init__(self, new_video: Callable[[], Any], new_photos: Callable[[], Any], min_interval_s: float) -> None:
        self.new_video, self.new_photos = new_video, new_photos
        self.min_interval_s = min_interval_s
        self.chosen: str | None = None
        self.source = None
        self.first: tuple[Frame, Intrinsics | None] | None = None

    @property
    def name(self) -> str:
        return self.chosen or VIDEO

    def __getattr__(self, attribute: str) -> Any:
        # what the engine asks of a pose source beyond the protocol (estimated_intrinsics, calibrating, ...)
        source = self.__dict__.get("source")
        if source is None:
            raise AttributeError(attribute)
        return getattr(source, attribute)

    def choose(self, first: Frame, second: Frame, intrinsics: Intrinsics | None) -> str:
        """Photos when the two frames are at least `min_interval_s` apart and the camera is known."""
        interval = second.timestamp - first.timestamp
        photos = self.min_interval_s > 0 and interval >= self.min_interval_s and intrinsics is not None
        return PHOTOS if photos else VIDEO

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        if self.source is not None:
            return self.source.track(frame, intrinsics)
        if self.first is None:
            self.first = (frame, intrinsics)
            return TrackingResult(np.eye(4), tracked=True, keyframe_hint=False, quality=0.0)
        self.chosen = self.choose(self.first[0], frame, intrinsics)
        self.source = self.new_photos() if self.chosen == PHOTOS else self.new_video()
        early = self.source.track(*self.first)
        self.first = None
        result = self.source.track(frame, intrinsics)
        result.events = early.events + result.events
        return result

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        if self.source is not None:
            self.source.keyframe_added(frame, pose)

    def state_dict(self) -> dict[str, Any]:
        waiting = None if self.first is None else {
            "index": self.first[0].index, "timestamp": self.first[0].timestamp, "image": self.first[0].image,
            "intrinsics": None if self.first[1] is None else self.first[1].to_dict()}
        return {"chosen": self.chosen, "first": waiting,
                "source": None if self.source is None else self.source.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.chosen = state["chosen"]
        self.source = None
        if self.chosen is not None:
            self.source = self.new_photos() if self.chosen == PHOTOS else self.new_video()
            self.source.load_state_dict(state["source"])
        first = state.get("first")
        self.first = None if first is None else (
            Frame(index=int(first["index"]), timestamp=float(first["timestamp"]), image=np.asarray(first["image"])),
            None if first["intrinsics"] is None else Intrinsics.from_dict(first["intrinsics"]))
