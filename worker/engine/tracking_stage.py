"""The tracking stage (ORB-SLAM's Tracking in our terms): frames in, each frame's pose out at once.

In the caller's thread, per frame: the session's pose source (worker.tracking: device poses, RGB-D odometry, visual
odometry or the model) -> the keyframe decision (the source's hint, else the motion selector) -> the trajectory,
which ties every frame to its reference keyframe. A new keyframe goes to the loop-closing stage as a pose-graph node
with its odometry edge (`publish_keyframe`); loop corrections come back through `apply_correction`, which moves the
keyframes (those made after the optimisation follow the newest optimised one) and bumps the revision, so the
published poses never jump. The stage never waits for mapping or loop closing. Frames larger than `max_side` (the
tracking resolution; 0: as they come) are tracked at that size: the pose does not depend on it, mapping keeps the
full frame.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import torch

from worker.data.frame import Frame
from worker.engine.keyframes import MotionKeyframeSelector
from worker.engine.loop_stage import GraphKeyframe
from worker.engine.stage_times import StageTimes
from worker.engine.trajectory import Trajectory
from worker.geometry import Intrinsics, sim3_inverse
from worker.tracking.base import TrackingResult


class TrackingStage:
    """Pose source -> keyframe decision -> trajectory (see the module docstring)."""

    def __init__(self, selector: MotionKeyframeSelector, publish_keyframe: Callable[[GraphKeyframe], None],
                 timings: StageTimes | None = None, max_side: int = 0) -> None:
        self.selector = selector
        self.max_side = max_side
        self.publish_keyframe = publish_keyframe
        self.timings = timings or StageTimes()
        self.pose_source = None  # chosen by the system from the first frame
        self.timing_stage = "frontend_tracking"
        self.trajectory = Trajectory()
        self.last_keyframe: int | None = None
        self.submap_of: dict[int, int] = {}
        self._tracked_frame: Frame | None = None  # the newest frame as the pose source saw it

    @property
    def revision(self) -> int:
        return self.trajectory.revision

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> tuple[TrackingResult, np.ndarray]:
        """The pose source's result for `frame` and its pose (float64 4x4, checked finite)."""
        with self.timings.measure(self.timing_stage):
            small = at_most(frame, self.max_side)
            if small is not frame and intrinsics is not None:
                intrinsics = intrinsics.scaled(small.width, small.height)
            tracking = self.pose_source.track(small, intrinsics)
        self._tracked_frame = small
        self.selector.observe(small.image)
        pose = np.asarray(tracking.pose, np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):  # a bug in the source: never passed on
            raise RuntimeError(f"frame {frame.index}: the pose source returned a non-finite pose")
        return tracking, pose

    def is_keyframe(self, tracking: TrackingResult, pose: np.ndarray, depth: np.ndarray | None = None,
                    camera: Intrinsics | None = None) -> bool:
        """The first frame always; then the source's hint when it gives one (False while lost), else the motion
        selector. `depth` (the frame's, sensor or the source's) and its `camera` let the selector measure motion
        against the scene's depth (any size: the camera is the frame's)."""
        if self.last_keyframe is None:
            self.selector.is_keyframe(pose, depth=depth, camera=camera)
            return True
        if tracking.keyframe_hint is False:
            return False
        return self.selector.is_keyframe(pose, force=bool(tracking.keyframe_hint), depth=depth, camera=camera)

    def add_keyframe(self, frame: Frame, tracked_pose: np.ndarray, submap_id: int, edge_kind: str | None = None
                     ) -> np.ndarray:
        """Insert keyframe `frame` in the trajectory, tell the pose source and publish its pose-graph node (with
        the odometry edge from the previous keyframe, of kind `edge_kind` when given); returns its world pose."""
        kf_id, previous = frame.index, self.last_keyframe
        world = self.trajectory.add_keyframe(kf_id, tracked_pose, reference=previous)
        node = GraphKeyframe(kf_id, world.copy(), scene_depth=self.selector.scene_depth)
        if previous is not None:
            node.previous = previous
            node.relative = (sim3_inverse(torch.from_numpy(self.trajectory.tracked_keyframe_poses[previous]))
                             @ torch.from_numpy(np.asarray(tracked_pose, np.float64))).numpy()
            node.kind = edge_kind or ("sequential" if self.submap_of.get(previous, submap_id) == submap_id
                                      else getattr(self.pose_source, "submap_seam", "inter_submap"))
        self.publish_keyframe(node)
        self.submap_of[kf_id] = submap_id
        self.last_keyframe = kf_id
        tracked = self._tracked_frame
        self.pose_source.keyframe_added(tracked if tracked is not None and tracked.index == frame.index
                                        else at_most(frame, self.max_side), tracked_pose)
        return world

    def add_frame(self, frame: Frame, tracked_pose: np.ndarray, is_keyframe: bool, submap_id: int) -> np.ndarray:
        """Record the frame against the newest keyframe; returns its world pose now."""
        return self.trajectory.add_frame(frame.index, frame.timestamp, self.last_keyframe, tracked_pose,
                                         is_keyframe, submap_id)

    def apply_correction(self, poses: dict[int, np.ndarray]) -> tuple[int, dict[int, np.ndarray]]:
        """Move the keyframes to optimised poses; those the optimisation did not know (made after it) follow the
        newest optimised keyframe before them. Returns (the new revision, the keyframes that moved)."""
        old = {k: v.copy() for k, v in self.trajectory.keyframe_poses.items()}
        moved = follow_corrections(old, {k: p for k, p in poses.items() if k in old})
        revision = self.trajectory.update_keyframes(moved)
        return revision, {k: p for k, p in moved.items() if not np.allclose(p, old[k], atol=1e-9)}

    def source_intrinsics(self, width: int, height: int) -> Intrinsics | None:
        """The pose source's camera estimate (self-calibration), at `width` x `height`; None when it has none."""
        estimate = getattr(self.pose_source, "estimated_intrinsics", None)
        if estimate is None or (estimate.width, estimate.height) == (width, height):
            return estimate
        return estimate.scaled(width, height)

    def state_dict(self, trajectory: dict[str, Any] | None = None) -> dict[str, Any]:
        """The stage's state; `trajectory` replaces the trajectory's full state (e.g. its chunked state)."""
        return {"trajectory": self.trajectory.state_dict() if trajectory is None else trajectory,
                "selector": self.selector.state_dict(),
                "last_keyframe": self.last_keyframe, "submap_of": [[k, v] for k, v in self.submap_of.items()],
                "pose_source": None if self.pose_source is None else self.pose_source.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.trajectory.load_state_dict(state["trajectory"])
        self.selector.load_state_dict(state["selector"])
        self.last_keyframe = state["last_keyframe"]
        self.submap_of = {int(k): int(v) for k, v in state["submap_of"]}
        if state.get("pose_source") and self.pose_source is not None:
            self.pose_source.load_state_dict(state["pose_source"])


def at_most(frame: Frame, max_side: int) -> Frame:
    """`frame` brought down (aspect kept) so that its long side is at most `max_side` (0: as it is): area-averaged
    colour, nearest depth (averaging would mix valid depth with holes), intrinsics scaled."""
    longest = max(frame.width, frame.height)
    if max_side <= 0 or longest <= max_side:
        return frame
    width = max(1, round(frame.width * max_side / longest))
    height = max(1, round(frame.height * max_side / longest))
    image = cv2.resize(frame.image, (width, height), interpolation=cv2.INTER_AREA)
    depth = None if frame.depth is None else cv2.resize(frame.depth, (width, height),
                                                          interpolation=cv2.INTER_NEAREST)
    intrinsics = None if frame.intrinsics is None else frame.intrinsics.scaled(width, height)
    return Frame(frame.index, frame.timestamp, image, intrinsics=intrinsics, depth=depth, pose=frame.pose,
                 gt_pose=frame.gt_pose)


def follow_corrections(current: dict[int, np.ndarray], corrected: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """`corrected` plus every keyframe of `current` it lacks, moved as the newest corrected keyframe before it."""
    out = dict(corrected)
    anchor: int | None = None
    for kf in sorted(current):
        if kf in corrected:
            anchor = kf
        elif anchor is not None:
            out[kf] = corrected[anchor] @ sim3_inverse(torch.from_numpy(current[anchor])).numpy() @ current[kf]
    return out
