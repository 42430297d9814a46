"""What flows into and out of the SLAM engine, frame by frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from worker.events import EngineEvent
from worker.geometry import Intrinsics


@dataclass
class Frame:
    """One camera frame.

    image: uint8 RGB [H, W, 3]. intrinsics: the camera when known. depth: metric z-depth float32 [H, W]
    (0 = invalid) when the stream carries it. pose: camera-to-world 4x4 float64 from the device or a dataset
    (used as a prior/fixed pose in posed mode). gt_pose: ground truth for evaluation only, never used by tracking.
    """

    index: int
    timestamp: float
    image: np.ndarray
    intrinsics: Intrinsics | None = None
    depth: np.ndarray | None = None
    pose: np.ndarray | None = None
    gt_pose: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[2] != 3 or self.image.dtype != np.uint8:
            raise ValueError(f"Frame.image must be uint8 [H, W, 3], got {self.image.dtype} {self.image.shape}")
        h, w = self.image.shape[:2]
        if self.depth is not None and self.depth.shape != (h, w):
            raise ValueError(f"Frame.depth must be [{h}, {w}], got {self.depth.shape}")
        for name in ("pose", "gt_pose"):
            value = getattr(self, name)
            if value is not None and np.asarray(value).shape != (4, 4):
                raise ValueError(f"Frame.{name} must be a 4x4 matrix")
        if self.intrinsics is not None and (self.intrinsics.width, self.intrinsics.height) != (w, h):
            raise ValueError(
                f"intrinsics are for {self.intrinsics.width}x{self.intrinsics.height} but the image is {w}x{h}"
            )

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @property
    def height(self) -> int:
        return self.image.shape[0]


@dataclass
class FrameResult:
    """What the engine says about a frame once the frontend has tracked it.

    pose: camera-to-world 4x4 (Sim(3) in monocular mode) in the current map frame; revision: the trajectory
    revision this pose belongs to (grows when a loop closure rewrites the past); events: what happened at it
    (worker.events), such as LoopClosed(revision=3, from_keyframe=40, to_keyframe=2).
    """

    index: int
    timestamp: float
    pose: np.ndarray
    is_keyframe: bool
    submap_id: int
    revision: int
    events: list[EngineEvent] = field(default_factory=list)
    tracked: bool = True  # False: tracking was lost at this frame and the pose is the last one held

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index, "timestamp": self.timestamp, "pose": np.asarray(self.pose, dtype=np.float64).tolist(),
            "is_keyframe": self.is_keyframe, "submap_id": self.submap_id, "revision": self.revision,
            "events": [event.to_dict() for event in self.events],
        }
