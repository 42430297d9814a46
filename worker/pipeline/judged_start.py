"""A session's first frames while its device poses are judged (`pose_mode` auto without depth).

Those frames get the device's poses (provisional), are kept, and make no keyframe; a session in a stored map looks
them up in it meanwhile, and once anchored there their poses are in the map's world. At the verdict every kept frame
goes through the chosen source from the first, as if the session had begun with it: with `seeded`, the map never
holds a keyframe on the device poses the images disagreed with (the keyframes' multi-view depth is made on the
visual odometry's poses). The verdict frame's result carries the replayed frames' events and the new revision.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from worker.data.frame import Frame, FrameResult
from worker.events import EngineEvent, PoseSourceChosen
from worker.geometry import Intrinsics
from worker.pipeline.tracking_stage import TrackingStage


class JudgedStart:
    """The frames kept while the device poses are judged (see the module docstring)."""

    def __init__(self, stage: TrackingStage) -> None:
        self.stage = stage
        self.frames: list[Frame] = []

    @property
    def judging(self) -> bool:
        """Whether the pose source is still judging the device poses: a live stream should skip no frame now
        (their triples need the frames as the camera took them; skipped ones would make a different verdict)."""
        return bool(getattr(self.stage.pose_source, "judging", False))

    def push(self, frame: Frame) -> FrameResult:
        """A frame while judging: the device's pose, kept; the verdict frame replays the kept ones."""
        stage = self.stage
        corrections = stage.apply_loop_corrections()  # a stored map's anchoring moves the world already
        tracking, pose = stage.track(frame, stage.camera.of_frame(frame))
        self.frames.append(frame)
        if self.judging:
            world = stage.trajectory.provisional(pose)
            if tracking.tracked:
                stage.query_map(frame, False, world)
            return FrameResult(frame.index, frame.timestamp, world, False, tracking.submap_id, stage.revision,
                               corrections + list(tracking.events), tracked=tracking.tracked)
        result = self.replay(tracking.events)
        result.events = corrections + result.events
        return result

    def conclude(self) -> list[EngineEvent]:
        """The stream ended while judging: decide on what was measured and replay; returns the events."""
        if not self.frames:
            return []
        decision = self.stage.pose_source.conclude(self.frames[-1].index)
        return self.replay(decision).events

    def replay(self, decision: list[EngineEvent]) -> FrameResult:
        """The kept frames through the chosen source, from the first; the last one's result, carrying the
        decision's `pose_source_chosen` event (with the frames replayed and the new revision) and the replayed
        frames' events."""
        stage, judged = self.stage, self.frames
        self.frames = []
        # No keyframe has a multi-view depth yet to measure motion against: the judging's triangulated points do
        stage.selector.set_scene_depth(getattr(stage.pose_source, "scene_depth", None))
        events: list[EngineEvent] = []
        for kept in judged:
            result = stage.process(kept)
            events += result.events
        revision = stage.trajectory.revise_frames({})  # the provisional poses of the judged frames are replaced
        chosen = [replace(e, frames_replayed=len(judged), revision=revision)
                  for e in decision if isinstance(e, PoseSourceChosen)]
        result.events = chosen + [e for e in decision if not isinstance(e, PoseSourceChosen)] + events
        result.revision = revision
        return result

    def state_dict(self) -> list[dict[str, Any]]:
        return [frame_state(f) for f in self.frames]

    def load_state_dict(self, frames: list[dict[str, Any]] | None) -> None:
        self.frames = [frame_from_state(f) for f in frames or []]


def frame_state(frame: Frame) -> dict[str, Any]:
    """A kept frame for a snapshot (arrays as they are; intrinsics as a dict)."""
    return {"index": frame.index, "timestamp": frame.timestamp, "image": frame.image, "depth": frame.depth,
            "pose": frame.pose, "gt_pose": frame.gt_pose,
            "intrinsics": None if frame.intrinsics is None else frame.intrinsics.to_dict()}


def frame_from_state(state: dict[str, Any]) -> Frame:
    def array(value: Any, dtype) -> np.ndarray | None:
        return None if value is None else np.asarray(value, dtype)

    return Frame(int(state["index"]), float(state["timestamp"]), np.asarray(state["image"], np.uint8),
                 intrinsics=None if state["intrinsics"] is None else Intrinsics.from_dict(state["intrinsics"]),
                 depth=array(state["depth"], np.float32), pose=array(state["pose"], np.float64),
                 gt_pose=array(state["gt_pose"], np.float64))
