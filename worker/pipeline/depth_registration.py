"""The session's depth, registered to the colour camera before any stage uses it, or checked for misregistration.

With `input.depth_camera` every frame's depth is moved into the colour camera (worker.data.registration); without
it, the first `input.detect_misregistration_frames` frames with depth are compared edge to edge, and a
`depth_misregistered` event says so when depth and colour do not line up (the session reports it as a warning).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from worker.data.frame import Frame
from worker.data.registration import MisregistrationDetector, register_depth
from worker.data.registration_config import DepthCameraConfig
from worker.events import EngineEvent
from worker.geometry import Intrinsics

# The misregistration search covers shifts up to this fraction of the image width (10 px at 320).
MAX_SHIFT_FRACTION = 0.03


class DepthRegistration:
    """Registers or checks each frame's depth (see the module docstring)."""

    def __init__(self, depth_camera: DepthCameraConfig | None, detect_frames: int) -> None:
        self.depth_camera = depth_camera
        self.detect_frames = detect_frames
        self.detector: MisregistrationDetector | None = None
        self.checked = depth_camera is not None or detect_frames <= 0
        self.verdict = None

    def apply(self, frame: Frame, colour: Intrinsics | None) -> tuple[Frame, list[EngineEvent]]:
        """The frame with its depth in the colour camera, and the events to report (a misregistration, once)."""
        if frame.depth is None:
            return frame, []
        if self.depth_camera is not None:
            return self._registered(frame, colour), []
        if self.checked:
            return frame, []
        if self.detector is None:
            shift = max(3, round(MAX_SHIFT_FRACTION * frame.width))
            self.detector = MisregistrationDetector(frames=self.detect_frames, max_shift=shift)
        self.detector.add(frame.image, frame.depth)
        if not self.detector.done:
            return frame, []
        self.checked = True
        self.verdict = self.detector.verdict()
        return frame, [self.verdict.to_event()] if self.verdict is not None and self.verdict.misregistered else []

    def _registered(self, frame: Frame, colour: Intrinsics | None) -> Frame:
        if colour is None:
            raise ValueError("depth_camera is set but the colour camera's intrinsics are unknown: give them with the "
                             "frames or the session")
        d = self.depth_camera
        h, w = frame.depth.shape
        depth_camera = Intrinsics(d.fx, d.fy, d.cx, d.cy, d.width, d.height).scaled(w, h)
        registered = register_depth(frame.depth, depth_camera, colour, np.asarray(d.depth_to_color, np.float64))
        return dataclasses.replace(frame, depth=registered)
