"""The pose sources a session can use, and the choice of one from the config and the first frame.

- "device": the poses the frames carry (ARKit/ARCore, a dataset);
- "rgbd_odometry": dense alignment of depth + intensity (worker.tracking.rgbd_odometry);
- "visual_odometry": monocular features, PnP and bundle adjustment (worker.tracking.visual_odometry);
- "model": the learned submap tracker (worker.frontend.tracker), the paper's path.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.events import Relocalized, TrackingLost
from worker.geometry import Intrinsics
from worker.tracking.base import TrackingResult
from worker.tracking.device_clock import DeviceClock, clock_state, load_clock_state, retimed

log = logging.getLogger(__name__)

TRACKING_CHOICES = ("auto", "device", "rgbd_odometry", "visual_odometry", "photos", "model")


def choose_tracking(requested: str, frame: Frame, uses_pose: bool, uses_depth: bool, custom_model: bool) -> str:
    """The pose source for a session whose first frame is `frame`.

    "auto": the device's poses when frames carry them, else RGB-D odometry when they carry depth, else visual
    odometry (the monocular mode: video or photos, worker.tracking.monocular_choice; "photos" is that mode too);
    the learned model instead of either odometry when a model other than the shipped synthetic one is configured
    (its weights are the user's choice). An explicit choice is checked against what the frame carries.
    """
    if requested not in TRACKING_CHOICES:
        raise ValueError(f"unknown tracking {requested!r}; choose one of {list(TRACKING_CHOICES)}")
    if requested == "auto":
        if uses_pose:
            return "device"
        if custom_model:
            return "model"
        return "rgbd_odometry" if uses_depth else "visual_odometry"
    if requested == "device" and not uses_pose:
        raise ValueError(f"tracking 'device' needs poses with the frames; frame {frame.index} has none")
    if requested == "rgbd_odometry" and not uses_depth:
        raise ValueError(f"tracking 'rgbd_odometry' needs depth with the frames; frame {frame.index} has none")
    return "visual_odometry" if requested == "photos" else requested  # the monocular mode, photos its strategy


class DevicePoses:
    """The frames' own poses (validated: finite, rigid up to a uniform scale). A frame without one (the device not
    ready, a gap in its log) holds the last pose and is reported lost until poses come again. `device_clock`, when
    set, re-times the poses first (worker.tracking.device_clock)."""

    name = "device"

    def __init__(self) -> None:
        self.last_pose: np.ndarray | None = None
        self.lost = False
        self.device_clock: DeviceClock | None = None

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        frame = retimed(self.device_clock, frame, intrinsics)
        if frame.pose is None:
            events = [] if self.lost else [TrackingLost(frame=frame.index, reason="the frame has no device pose")]
            self.lost = True
            held = np.eye(4) if self.last_pose is None else self.last_pose
            return TrackingResult(held.copy(), tracked=False, keyframe_hint=False, events=events)
        pose = np.asarray(frame.pose, np.float64)
        if not np.all(np.isfinite(pose)):
            raise ValueError(f"frame {frame.index}: the pose is not finite")
        events = [Relocalized(frame=frame.index, method="device")] if self.lost else []
        self.last_pose, self.lost = pose.copy(), False
        return TrackingResult(pose.copy(), events=events)

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """Nothing to do: the device keeps its own map."""

    def state_dict(self) -> dict[str, Any]:
        return {"last_pose": [] if self.last_pose is None else self.last_pose, "lost": self.lost,
                **clock_state(self.device_clock)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        load_clock_state(self.device_clock, state)
        last = np.asarray(state.get("last_pose", []), np.float64)
        self.last_pose = last.reshape(4, 4) if last.size == 16 else None
        self.lost = bool(state.get("lost", False))


class ModelTracking:
    """The learned submap tracker as a pose source: each frame through the recurrent model (paper 4.1)."""

    name = "model"

    def __init__(self, tracker, bag, long_side: int, estimate_intrinsics) -> None:
        self.tracker, self.bag, self.long_side = tracker, bag, long_side
        self._estimate_intrinsics = estimate_intrinsics
        self.model_intrinsics: Intrinsics | None = None  # at model resolution, given or estimated

    def predict(self, frame: Frame, intrinsics: Intrinsics | None):
        """(prep, tracked): the preprocessed frame and the tracker's output for it."""
        from worker.frontend.preprocess import prepare_image, resample_for

        prep = prepare_image(frame.image, intrinsics, long_side=self.long_side,
                             resample=resample_for(self.tracker.model))
        tracked = self.tracker.track(frame.index, prep.tensor, prep.intrinsics or self.model_intrinsics)
        self.bag.add_finished(self.tracker.pop_finished_submaps())
        if self.model_intrinsics is None:
            self.model_intrinsics = prep.intrinsics or self._estimate_intrinsics(tracked.surfels, prep)
        return prep, tracked

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        prep, tracked = self.predict(frame, intrinsics)
        return TrackingResult(tracked.pose_world.numpy(), keyframe_hint=bool(tracked.is_keyframe),
                              submap_id=int(tracked.submap_id), prediction=(prep, tracked))

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The tracker chose the keyframe itself."""

    def state_dict(self) -> dict[str, Any]:
        return {}  # the tracker and the bag are snapshot by the engine (loop closure shares them)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """See state_dict."""
