"""The tracking stage (ORB-SLAM's Tracking in our terms): frames in, each frame's pose out at once.

In the caller's thread, per frame (`process`): the session's pose source (worker.tracking: device poses, RGB-D
odometry, visual odometry or the model) -> its events (worker.pipeline.pose_events) -> the depth source sees the frame
(worker.pipeline.depth_sources) -> the keyframe decision (the source's hint, else the motion selector) -> the
trajectory, which ties every frame to its reference keyframe. A new keyframe goes to the loop-closing stage as a
pose-graph node with its odometry edge, to the depth source, whose jobs go on to the mapping stage as they are
ready, and, as a loop query, to loop closing (or from mapping, once it has built the keyframe's multi-view depth).
Loop corrections come back through `apply_loop_corrections`, which moves the keyframes (those made after the
optimisation follow the newest optimised one), the jobs not in the map yet and the map, and bumps the revision, so
the published poses never jump. The stage never waits for mapping or loop closing. Frames larger than `max_side`
(the tracking resolution; 0: as they come) are tracked at that size: the pose does not depend on it, mapping keeps
the full frame.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
import torch

from worker.data.frame import Frame, FrameResult
from worker.events import DriftCorrected, EngineEvent, MapsMerged, PosesRefined, Relocalized
from worker.geometry import Intrinsics, nearest_sim3, sim3_inverse
from worker.maps.session_in_map import MapQuery, SessionInMap
from worker.pipeline.depth_sources.base import DepthSource
from worker.pipeline.keyframes import MotionKeyframeSelector
from worker.pipeline.loop_stage import GraphKeyframe, LoopClosingStage, LoopQuery
from worker.pipeline.map_jobs import PoseUpdateJob
from worker.pipeline.mapping_stage import MappingStage
from worker.pipeline.pose_events import PoseEvents
from worker.pipeline.session_camera import SessionCamera
from worker.pipeline.stage_times import StageTimes
from worker.pipeline.trajectory import Trajectory
from worker.tracking.base import TrackingResult

# The counter each kind of correction counts in.
CORRECTION_COUNTERS = {MapsMerged: "maps_merged", DriftCorrected: "drift_corrections",
                       Relocalized: "map_relocalizations"}

log = logging.getLogger(__name__)


class TrackingStage:
    """Pose source -> keyframe decision -> trajectory (see the module docstring)."""

    def __init__(self, selector: MotionKeyframeSelector, camera: SessionCamera, counters: dict[str, float],
                 timings: StageTimes | None = None, max_side: int = 0) -> None:
        self.selector = selector
        self.camera = camera
        self.counters = counters
        self.max_side = max_side
        self.timings = timings or StageTimes()
        self.trajectory = Trajectory()
        self.last_keyframe: int | None = None
        self.submap_of: dict[int, int] = {}
        self._tracked_frame: Frame | None = None  # the newest frame as the pose source saw it
        # Chosen from the session's first frame (worker.slam): the pose source, where keyframe surfels come from
        # (None without mapping), the stages downstream and how keyframes query loops.
        self.pose_source = None
        self.timing_stage = "frontend_tracking"
        self.depth_source: DepthSource | None = None
        self.mapping: MappingStage | None = None
        self.loop_closing: LoopClosingStage | None = None
        self.loop_queries: str | None = None  # "sensor", "after_depth" (multi-view, from mapping), "model" or None
        self.model_intrinsics = None  # () -> the model's camera, for its loop queries
        self.with_depth = False
        self.events = PoseEvents(self.trajectory, self.loop_closing_submit, counters)
        self.last_frame: tuple[Frame, bool] | None = None  # the newest frame, when not a keyframe, and if tracked
        self.last_frame_mapped: int | None = None  # the final frame's index when finish() mapped it too
        self.in_map: SessionInMap | None = None  # the stored map the session runs in (worker.maps), if any
        self.corrections_taken = 0  # loop-closing corrections applied so far
        self._source_adjustment: Future | None = None  # the pose source's final adjustment, begun at the finish
        self._source_has_points = False  # the pose source has seen points (its poses have a scale of their own)

    def loop_closing_submit(self, item) -> None:
        """Submit `item` to the loop-closing stage the session has now."""
        self.loop_closing.submit(item)

    # -- the frame path ------------------------------------------------------------------------------------------
    def process(self, frame: Frame) -> FrameResult:
        """One frame through the pose source, the keyframe decision, mapping and loop closure."""
        intrinsics = self.camera.of_frame(frame)
        events = self.apply_loop_corrections()
        tracking, pose = self.track(frame, intrinsics)
        events += self.events.on_tracked(tracking.events)
        prediction = tracking.prediction
        if self.depth_source is not None:
            prediction = self.depth_source.observe(frame, pose, tracking, intrinsics) or prediction
        self.counters["frames_tracked"] += int(tracking.tracked)
        is_kf = self.is_keyframe(tracking, pose, *self._scene_view(frame, tracking))
        if is_kf:
            world = self.add_keyframe(frame, pose, submap_id=tracking.submap_id,
                                      edge_kind="restart" if self.events.restart_seam else None)
            self.events.restart_seam = False
            self.counters["keyframes"] += 1
            if self.depth_source is not None:
                self.depth_source.add_keyframe(frame, world, tracking, self.loop_queries == "after_depth")
                if not self.depth_source.needs_later_frames:  # in the map before a loop closure can move it
                    self.hand_to_mapping()
            events += self._query_loops(frame, prediction)
        events += self.events.after_keyframe_decision(tracking.events, frame.index if is_kf else None,
                                                      tracking.submap_id, pose, self.last_keyframe)
        world = self.add_frame(frame, pose, is_kf, tracking.submap_id, tracking.anchor)
        if tracking.tracked:
            self.query_map(frame, is_kf, world, tracking.depth)
        self.last_frame = None if is_kf else (frame, tracking.tracked)
        self.hand_to_mapping()
        return FrameResult(frame.index, frame.timestamp, world, is_kf, tracking.submap_id, self.revision, events,
                           tracked=tracking.tracked)

    def _scene_view(self, frame: Frame, tracking: TrackingResult) -> tuple[np.ndarray | None, Intrinsics | None]:
        """The depth the keyframe selector measures motion against, and the frame's camera: the source's depth
        (sensor, or the points it triangulated), else the frame's sensor depth; without either (posed RGB), the
        selector gets the depth source's typical scene depth (multi-view stereo's newest keyframe)."""
        depth = tracking.depth if tracking.depth is not None else (frame.depth if self.with_depth else None)
        if depth is None and self.depth_source is not None and self.depth_source.name == "mvs":
            self.selector.set_scene_depth(self.depth_source.scene_depth())
        camera = self.camera.of_frame(frame) or self.source_intrinsics(frame.width, frame.height)
        return depth, camera

    def _query_loops(self, frame: Frame, prediction) -> list[EngineEvent]:
        """Queue loop closure for a new keyframe: against its sensor depth (ORB + PnP + ICP) or the model's hidden
        states; with multi-view depth the mapping stage queues it once it has built the keyframe's depth. Returns
        the events of corrections an inline stage has made already."""
        if self.loop_queries in (None, "after_depth"):
            return []
        if self.loop_queries == "sensor":
            intr = self.camera.for_frame(frame)
            image = torch.from_numpy(frame.image).permute(2, 0, 1)[None].float() / 255.0
            self.loop_closing.submit(LoopQuery(frame.index, image, intr, torch.from_numpy(
                np.asarray(frame.depth, np.float32)), intr.matrix()))
        else:
            self.loop_closing.submit(LoopQuery(frame.index, prediction[0].tensor, self.model_intrinsics()))
        return self.apply_loop_corrections() if not self.loop_closing.pending else []

    def query_map(self, frame: Frame, is_keyframe: bool, world: np.ndarray, source_depth: np.ndarray | None = None
                  ) -> None:
        """Hand the frame to loop closing to find it in the stored map the session runs in: every frame until
        the session is anchored in the map (loop closing sheds those it is late for), then each keyframe. Without
        sensor depth, the points the pose source sees in the frame (`source_depth`, its own units, at the tracked
        size) go along until the anchoring: they measure an up-to-scale session's scale in the map, which looks
        itself up only from the first frame with such points (before, its poses have no scale of their own)."""
        in_map = self.in_map
        if in_map is None or (in_map.anchored and not is_keyframe):
            return
        if not in_map.metric and not self._source_has_points:  # an up-to-scale source's poses mean nothing yet
            if source_depth is None or not np.any(source_depth > 0):
                return
            self._source_has_points = True
        small = self._tracked_frame if self._tracked_frame is not None and self._tracked_frame.index == frame.index \
            else at_most(frame, self.max_side)
        K = self.camera.for_frame(frame).scaled(small.width, small.height).matrix()
        gray = cv2.cvtColor(np.ascontiguousarray(small.image), cv2.COLOR_RGB2GRAY)
        depth = None if not self.with_depth or small.depth is None else np.asarray(small.depth, np.float32)
        points = None
        if depth is None and not in_map.anchored and source_depth is not None \
                and source_depth.shape == gray.shape:
            v, u = np.nonzero(source_depth > 0)
            points = np.stack([u + 0.5, v + 0.5, source_depth[v, u]], axis=1).astype(np.float32)
        self.loop_closing.submit(MapQuery(frame.index, is_keyframe, np.asarray(world, np.float64).copy(), gray,
                                          np.asarray(K, np.float64), depth, self.corrections_taken, points))

    def hand_to_mapping(self, force: bool = False) -> None:
        """The depth source's ready jobs to the mapping stage; none while the pose source is still estimating the
        camera (unless `force`)."""
        if self.depth_source is None or self.mapping is None:
            return
        hold = bool(getattr(self.pose_source, "calibrating", False))
        for job in self.depth_source.jobs(self.trajectory.pose_at, hold=hold, force=force):
            self.mapping.submit(job)

    def map_last_frame(self) -> None:
        """At the end of a session the newest view enters the map too (when it is not a keyframe already and was
        tracked): it is the view a user looks at first. Keyframe-like surfels from its depth, sensor or multi-view;
        not a pose-graph node (nothing moves it any more)."""
        if self.last_frame is None or self.depth_source is None:
            return
        frame, tracked = self.last_frame
        self.last_frame = None
        if tracked and self.depth_source.add_last_frame(frame, self.trajectory.pose_at(frame.index)):
            self.last_frame_mapped = frame.index

    def apply_loop_corrections(self) -> list[EngineEvent]:
        """Apply the loop-closing stage's new corrections (in order): the trajectory, the jobs not in the map yet
        and the map move to the optimised keyframe poses. Returns their events."""
        events = []
        for correction in self.loop_closing.take_corrections():
            self.corrections_taken += 1
            if correction.world_move is not None:
                self.trajectory.move_world(correction.world_move)
            revision, changed = self.apply_correction(correction.poses)
            self._move_map(changed)
            counter = CORRECTION_COUNTERS.get(type(correction.event), "loops")
            self.counters[counter] = self.counters.get(counter, 0) + 1
            events.append(replace(correction.event, revision=revision))
        return events

    def begin_source_adjustment(self) -> None:
        """Begin the pose source's final adjustment of its keyframes (visual odometry's `keyframe_corrections`), if
        it has one, in a thread of its own: it reads only the source's own records, which no frame changes any
        more, so it runs while the mapping stage drains (`apply_source_refinement` takes its result)."""
        adjust = getattr(self.pose_source, "keyframe_corrections", None)
        if adjust is None or self._source_adjustment is not None:
            return
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="source-adjustment")
        self._source_adjustment = pool.submit(adjust)
        pool.shutdown(wait=False)  # the thread ends with its one job

    def _source_adjustment_result(self) -> dict[int, np.ndarray]:
        """The final adjustment's keyframe moves ({} without one; a failure is logged and the poses stay)."""
        future, self._source_adjustment = self._source_adjustment, None
        if future is None:
            return {}
        try:
            return future.result()
        except Exception:  # a bug there must not cost the session its finish: the trajectory stays as it was
            log.exception("the pose source's final adjustment failed; the poses stay as they were")
            return {}

    def apply_source_refinement(self) -> list[EngineEvent]:
        """The pose source's own refinement of its poses, where it has one (photo registration's bundle adjustment
        of every photo, `refined_poses`; visual odometry's final bundle adjustment, `keyframe_corrections`): the
        keyframes move to it as after a loop (the frames between them, the
        jobs not in the map yet and the map follow), the other frames it posed are put where it says. Returns the
        `poses_refined` event, or nothing."""
        refine = getattr(self.pose_source, "refined_poses", None)
        poses = refine() if refine is not None else {}
        if not poses:  # visual odometry's final bundle adjustment: its keyframes' moves, the frames follow
            self.begin_source_adjustment()
            moves = self._source_adjustment_result()
            poses = self.trajectory.source_corrected_poses(moves) if moves else {}
        if not poses:
            return []
        trajectory = self.trajectory
        old = {k: pose.copy() for k, pose in trajectory.keyframe_poses.items()}
        _, changed = self.apply_correction({k: p for k, p in poses.items() if k in old})
        trajectory.spread_keyframe_moves(old)
        revision = trajectory.place_frames({i: p for i, p in poses.items() if i not in old})
        self._move_map(changed)
        return [PosesRefined(keyframes=len(changed), revision=revision)]

    def _move_map(self, changed: dict[int, np.ndarray]) -> None:
        """The jobs not in the map yet and the map follow keyframes that moved."""
        if self.depth_source is not None and self.mapping is not None:
            self.depth_source.move(changed)
            if changed:
                self.mapping.submit(PoseUpdateJob(changed))

    # -- the steps -----------------------------------------------------------------------------------------------
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
        node = GraphKeyframe(kf_id, world.copy(), scene_depth=self.selector.scene_depth,
                             corrections_seen=self.corrections_taken)
        if previous is not None:
            node.previous = previous
            node.relative = (sim3_inverse(torch.from_numpy(self.trajectory.tracked_keyframe_poses[previous]))
                             @ torch.from_numpy(np.asarray(tracked_pose, np.float64))).numpy()
            node.kind = edge_kind or ("sequential" if self.submap_of.get(previous, submap_id) == submap_id
                                      else getattr(self.pose_source, "submap_seam", "inter_submap"))
        self.loop_closing.submit(node)
        self.submap_of[kf_id] = submap_id
        self.last_keyframe = kf_id
        tracked = self._tracked_frame
        self.pose_source.keyframe_added(tracked if tracked is not None and tracked.index == frame.index
                                        else at_most(frame, self.max_side), tracked_pose)
        return world

    def add_frame(self, frame: Frame, tracked_pose: np.ndarray, is_keyframe: bool, submap_id: int,
                  anchor: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """Record the frame against the newest keyframe (and the earlier keyframe the source measured it against,
        `anchor`); returns its world pose now."""
        return self.trajectory.add_frame(frame.index, frame.timestamp, self.last_keyframe, tracked_pose,
                                         is_keyframe, submap_id, anchor)

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
                "corrections_taken": self.corrections_taken,
                "pose_source": None if self.pose_source is None else self.pose_source.state_dict(),
                "depth_source": None if self.depth_source is None else self.depth_source.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.trajectory.load_state_dict(state["trajectory"])
        self.selector.load_state_dict(state["selector"])
        self.last_keyframe = state["last_keyframe"]
        self.submap_of = {int(k): int(v) for k, v in state["submap_of"]}
        self.corrections_taken = int(state.get("corrections_taken", 0))
        if state.get("pose_source") and self.pose_source is not None:
            self.pose_source.load_state_dict(state["pose_source"])
        if state.get("depth_source") is not None and self.depth_source is not None:
            self.depth_source.load_state_dict(state["depth_source"])


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
            out[kf] = nearest_sim3(corrected[anchor] @ sim3_inverse(torch.from_numpy(current[anchor])).numpy()
                                   @ current[kf])  # a keyframe may follow many corrections: no shear may build up
    return out
