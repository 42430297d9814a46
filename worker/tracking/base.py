"""What every pose source returns, and the protocol it implements.

A pose source turns a frame into a camera-to-world pose: the device's own poses, dense RGB-D odometry, monocular
visual odometry or the learned submap tracker. `SlamSystem` picks one per session (`tracking.source`) and the rest
of the pipeline (keyframes, loop closure, pose graph, map) sees only a `TrackingResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from worker.data.frame import Frame
from worker.events import EngineEvent
from worker.geometry import Intrinsics


@dataclass
class TrackingResult:
    """One frame's tracking outcome.

    pose: camera-to-world 4x4 Sim(3) in the source's world frame, always finite (while lost: the last good pose
    moved by the motion model, never a jump). keyframe_hint: the source asks for a keyframe here (None: let the
    motion-based selector decide; False: the source vetoes one, e.g. while lost). depth: per-pixel z-depth
    [H, W] float32 at the frame's resolution in the pose's units (0 = unknown), when the source has it.
    tracked: False while tracking is lost. events: what happened (worker.events), such as TrackingLost(reason=...).
    submap_id: the model's submap (0 for other sources). prediction: the learned model's per-pixel output for this
    frame (its preprocessed image and surfels) when the model ran. quality: how well the pose is supported, 0 to 1
    (visual odometry: the pose's inliers as a share of the last keyframe's tracked points; 0 for a placeholder),
    None when the source does not say. translation_measured: False where only the orientation was measured and the
    position was held or predicted (visual odometry's turn models): a device's motion knows it better.
    anchor: (keyframe id, pose relative to it) when the source measured this frame against an earlier engine
    keyframe it came back to (RGB-D odometry's reused places): the session's finish places the frame on that
    keyframe's corrected pose rather than on the drift accumulated since (worker.pipeline.trajectory).
    """

    pose: np.ndarray
    tracked: bool = True
    keyframe_hint: bool | None = None
    depth: np.ndarray | None = None
    events: list[EngineEvent] = field(default_factory=list)
    submap_id: int = 0
    prediction: Any = None
    quality: float | None = None
    translation_measured: bool = True
    anchor: tuple[int, np.ndarray] | None = None


class PoseSource(Protocol):
    """A tracking strategy: frames in order -> `TrackingResult`s; its state can be snapshot and restored."""

    name: str

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        """Track the next frame (its index grows)."""

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The engine made `frame` a keyframe at `pose` (the source may use it as its new reference)."""

    def state_dict(self) -> dict[str, Any]:
        """Everything to continue, as msgpack-able values (numpy arrays allowed)."""

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from `state_dict()`."""
