"""RGB-only sessions with `tracking.source` auto: video or photos, told apart by the time between their first
frames. Video (the first three frames less than `tracking.photos.min_interval_s` apart, either step) goes to visual
odometry, whose optical flow follows small steps; photos (both steps that long or longer: a person taking photos, not
a camera's clock with a late frame) go to photo registration (worker.tracking.photos), which matches features
however far apart the views are. The first frames wait for the third (placeholder poses, as visual odometry gives
them before its first map), then all go through the chosen source. Without intrinsics the frames are video at once
(photo registration needs the camera; visual odometry estimates it)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.tracking.base import TrackingResult

VIDEO, PHOTOS = "visual_odometry", "photos"


DECIDING_FRAMES = 3  # the frames whose two steps decide


class MonocularChoice:
    """Visual odometry or photo registration, chosen at the third frame (module docstring). `new_video` and
    `new_photos` build the two sources."""

    def __init__(self, new_video: Callable[[], Any], new_photos: Callable[[], Any], min_interval_s: float) -> None:
        self.new_video, self.new_photos = new_video, new_photos
        self.min_interval_s = min_interval_s
        self.chosen: str | None = None
        self.source = None
        self.waiting: list[tuple[Frame, Intrinsics | None]] = []
        self.keyframes: dict[int, tuple[Frame, np.ndarray]] = {}  # engine keyframes among the waiting frames

    @property
    def name(self) -> str:
        return self.chosen or VIDEO

    @property
    def keeps_every_frame(self) -> bool:
        """A live stream skips no frame while the choice waits for its frames, nor once they are photos."""
        return self.chosen != VIDEO

    def __getattr__(self, attribute: str) -> Any:
        # what the engine asks of a pose source beyond the protocol (estimated_intrinsics, calibrating, ...)
        source = self.__dict__.get("source")
        if source is None:
            raise AttributeError(attribute)
        return getattr(source, attribute)

    def choose(self, frames: list[Frame]) -> str:
        """Photos when every step between `frames` is at least `min_interval_s`."""
        steps = np.diff([f.timestamp for f in frames])
        return PHOTOS if self.min_interval_s > 0 and len(steps) and steps.min() >= self.min_interval_s else VIDEO

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        if self.source is not None:
            return self.source.track(frame, intrinsics)
        self.waiting.append((frame, intrinsics))
        if intrinsics is not None and len(self.waiting) < DECIDING_FRAMES:
            return TrackingResult(np.eye(4), tracked=True, keyframe_hint=False, quality=0.0)
        self.chosen = VIDEO if intrinsics is None else self.choose([f for f, _ in self.waiting])
        self.source = self.new_photos() if self.chosen == PHOTOS else self.new_video()
        early = []
        for item in self.waiting[:-1]:  # as if the source had had them as they came, keyframes told
            early.append(self.source.track(*item))
            if item[0].index in self.keyframes:
                self.source.keyframe_added(*self.keyframes[item[0].index])
        self.waiting, self.keyframes = [], {}
        result = self.source.track(frame, intrinsics)
        result.events = [e for r in early for e in r.events] + result.events
        return result

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        if self.source is not None:
            self.source.keyframe_added(frame, pose)
        else:  # the session's first frame: told to the source once it tracks that frame
            self.keyframes[frame.index] = (frame, pose.copy())

    def state_dict(self) -> dict[str, Any]:
        waiting = [{"index": f.index, "timestamp": f.timestamp, "image": f.image,
                    "intrinsics": None if k is None else k.to_dict()} for f, k in self.waiting]
        keyframes = [{"index": i, "pose": pose} for i, (_, pose) in self.keyframes.items()]
        return {"chosen": self.chosen, "waiting": waiting, "keyframes": keyframes,
                "source": None if self.source is None else self.source.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "chosen" not in state:  # a snapshot of a version before the choice: visual odometry's own state
            state = {"chosen": VIDEO, "source": state}
        self.chosen = state["chosen"]
        self.source = None
        if self.chosen is not None:
            self.source = self.new_photos() if self.chosen == PHOTOS else self.new_video()
            self.source.load_state_dict(state["source"])
        self.waiting = [(Frame(index=int(w["index"]), timestamp=float(w["timestamp"]), image=np.asarray(w["image"])),
                         None if w["intrinsics"] is None else Intrinsics.from_dict(w["intrinsics"]))
                        for w in state.get("waiting", [])]
        frames = {f.index: f for f, _ in self.waiting}
        self.keyframes = {int(k["index"]): (frames[int(k["index"])], np.asarray(k["pose"], np.float64).reshape(4, 4))
                          for k in state.get("keyframes", []) if int(k["index"]) in frames}
