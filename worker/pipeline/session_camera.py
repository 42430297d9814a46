"""The session's camera: given with the frames or the session, else estimated by the pose source or the model."""

from __future__ import annotations

from collections.abc import Callable

from worker.data.frame import Frame
from worker.geometry import Intrinsics


class SessionCamera:
    """Resolves a frame's camera: its own intrinsics, else the session's (scaled to the frame), else the pose
    source's estimate (`source_estimate(width, height)`: self-calibration), else the learned model's
    (`model_estimate(width, height)`, set when the model runs)."""

    def __init__(self, given: Intrinsics | None, source_estimate: Callable[[int, int], Intrinsics | None]) -> None:
        self.given = given
        self.source_estimate = source_estimate
        self.model_estimate: Callable[[int, int], Intrinsics | None] | None = None
        self.frame_size: tuple[int, int] | None = None  # the session's frames, set by the first

    def of_frame(self, frame: Frame) -> Intrinsics | None:
        """The frame's camera as given: its own intrinsics, else the session's at the frame's size."""
        if frame.intrinsics is not None:
            return frame.intrinsics
        if self.given is None:
            return None
        if (self.given.width, self.given.height) != (frame.width, frame.height):
            return self.given.scaled(frame.width, frame.height)
        return self.given

    def for_frame(self, frame: Frame) -> Intrinsics:
        """The frame's camera: given, else the pose source's estimate (raises when there is neither)."""
        return self.of_frame(frame) or self.for_size(frame.width, frame.height)

    def for_size(self, width: int, height: int) -> Intrinsics:
        """The session's camera at `width` x `height`: given, else the pose source's estimate."""
        camera = self.given.scaled(width, height) if self.given is not None else self.source_estimate(width, height)
        if camera is None:
            raise ValueError("no intrinsics for this session: give them with the frames or the session")
        return camera

    def estimated(self) -> Intrinsics | None:
        """The camera at the input frames' resolution: given, else the pose source's estimate (visual odometry's
        self-calibration, RGB-D odometry's guess), else the model's (from its points)."""
        if self.frame_size is None:
            return self.given
        if self.given is not None:
            if (self.given.width, self.given.height) != tuple(self.frame_size):
                return self.given.scaled(*self.frame_size)  # frames worked on smaller than the camera given
            return self.given
        from_source = self.source_estimate(*self.frame_size)
        if from_source is not None or self.model_estimate is None:
            return from_source
        return self.model_estimate(*self.frame_size)
