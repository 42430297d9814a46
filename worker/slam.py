"""The SLAM system: one object per session, frame in -> pose out, with a 2DGS map behind it.

Three stages, each with its own input queue and thread (the Tracking / LocalMapping / LoopClosing split of
ORB-SLAM3): the tracking stage (worker.engine.tracking_stage, in the caller's thread: pose source, keyframe
decision, trajectory) publishes each frame's pose at once;
the mapping stage (worker.engine.mapping_stage) builds keyframe depth and maps keyframes (voxelize, prune, fuse,
refine, loop correction), shedding work when it falls behind; the loop-closing stage (worker.engine.loop_stage)
keeps the pose graph, detects and verifies loops and hands optimised keyframe poses back, which tracking applies as
a new trajectory revision. Tracking never waits for either. `SlamConfig.threaded=False` runs every stage inline in
the caller: deterministic.

One frame path: pose source -> keyframe selection -> map job -> loop closure. The pose source (worker.tracking) is
chosen once per session from `frontend.tracking` and the first frame (see `choose_tracking`):
- device (frames carry `pose` and `input.pose_mode != "ignore"`, mode "posed"): the given poses are the odometry,
  used as priors in the pose graph ("prior", loop closures can still correct them) or kept as they are ("fixed");
  with "seeded" (and "auto" with depth), RGB-D or visual odometry tracks from the device's motion and the device
  poses are keyframe priors (worker.tracking.seeded); "auto" without depth is "prior" where the first frames show
  the device poses agree with the images, else "seeded" (worker.tracking.pose_choice): those frames get the
  device's poses meanwhile and no keyframe, and go through the chosen source from the first at the verdict;
- rgbd_odometry (depth, no poses): dense photometric + geometric alignment to a reference keyframe;
- visual_odometry (RGB only): features, PnP against a local map, windowed bundle adjustment;
- model (mode "monocular"): the feed-forward model tracks submaps (worker.frontend.tracker), the paper's path.
Surfels come from what the frames carry, whichever source ran (`depth_source`): the frame's depth ("sensor",
`input.use_depth`; means from the unprojected depth, other attributes from the model or, with
`input.surfel_init="depth"`, from image and depth alone), else multi-view stereo on the tracked poses ("mvs",
worker.engine.keyframe_depth, built in the backend thread), or the model's prediction ("model"). Keyframes follow
the source's hint, else the motion-based selector.

`snapshot()` writes everything needed to continue (config, model id, pose source, tracker, bag of hidden states,
pose graph, trajectory, keyframes waiting for depth, map, counters) as msgpack; `SlamSystem.restore(data)`
continues from it in any process. `begin_snapshot()` takes the same without waiting: the tracking state at once,
each stage's at a marker in its queue once it has done what came before (`SnapshotFuture`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from worker.config import SlamConfig
from worker.data.frame import Frame, FrameResult
from worker.depth.border_planes import BorderSettings
from worker.depth.world_planes import PlaneSettings
from worker.engine.backend import KeyframeJob, PoseUpdateJob
from worker.engine.depth_registration import DepthRegistration
from worker.engine.finish_status import FinishStatus
from worker.engine.keyframe_depth import KeyframeDepth
from worker.engine.keyframes import MotionKeyframeSelector
from worker.engine.loop_closer import DepthKeyframePoints, LoopCloser
from worker.engine.loop_stage import CameraUpdate, LoopClosingStage, LoopCorrection, LoopQuery, MapJoin
from worker.engine.mapping_stage import MappingStage
from worker.engine.snapshot_future import SnapshotFuture
from worker.engine.stage_times import StageTimes
from worker.engine.surfel_init import grid_from_depth, grid_from_prediction
from worker.engine.tracking_stage import TrackingStage
from worker.engine.trajectory import Trajectory
from worker.geometry import Intrinsics, sim3_inverse
from worker.loop.pose_graph import DEFAULT_SIGMAS, EdgeSigmas, Sim3PoseGraph
from worker.serialization import pack, unpack
from worker.tracking.sources import DevicePoses, ModelTracking, choose_tracking

log = logging.getLogger(__name__)

SNAPSHOT_FORMAT = "flashmono.slam/2"
# Snapshots of format 1 (one dict, made after waiting for the backend) restore too: format 2 splits the same keys
# into the tracking, mapping and loop-closing parts.
SNAPSHOT_FORMATS = ("flashmono.slam/1", SNAPSHOT_FORMAT)
# Log-scale standard deviation of pose-graph edges when poses and depth are metric: the scale is known.
METRIC_LOG_SCALE_SIGMA = 1e-4
# The engine's mode (metrics, stats) for each pose source.
MODE_OF_TRACKING = {"device": "posed", "model": "monocular", "rgbd_odometry": "rgbd_odometry",
                    "visual_odometry": "visual_odometry"}
TRACKING_OF_MODE = {mode: tracking for tracking, mode in MODE_OF_TRACKING.items()}


def _w2c(pose_c2w: np.ndarray | torch.Tensor) -> torch.Tensor:
    return sim3_inverse(torch.as_tensor(np.asarray(pose_c2w, np.float64))).to(torch.float32)


class SlamSystem:
    """Monocular / posed / RGB-D 2DGS SLAM over a stream of `Frame`s (see the module docstring)."""

    def __init__(self, config: SlamConfig | None = None, intrinsics: Intrinsics | None = None) -> None:
        self.config = config if config is not None else SlamConfig.preset("default")
        if not isinstance(self.config, SlamConfig):
            raise ValueError(f"config must be a SlamConfig, got {type(self.config).__name__}")
        torch.set_num_threads(self.config.num_threads)
        self.intrinsics = intrinsics
        self.mode: str | None = None  # MODE_OF_TRACKING[self.tracking], set by the first frame
        self.tracking: str | None = None  # the pose source's name
        self._model: ModelTracking | None = None  # the learned model, as pose source or surfel predictor
        self.timings = StageTimes()  # the runtime breakdown of paper appendix E
        self._with_depth = False
        self.loop_stage = self._new_loop_stage(self._new_pose_graph(), closer=None, depth_points=None)
        fc = self.config.frontend
        self.tracking_stage = TrackingStage(
            MotionKeyframeSelector(fc.keyframe_every, fc.keyframe_translation, fc.keyframe_rotation_deg,
                                   fc.keyframe_blur_ratio, fc.keyframe_blur_delay, depth_ratio=fc.keyframe_parallax,
                                   min_overlap=fc.keyframe_min_overlap, approach=fc.keyframe_approach),
            publish_keyframe=lambda node: self.loop_stage.submit(node), timings=self.timings,
            max_side=self.config.tracking.max_side)
        self._traj = self.tracking_stage.trajectory
        self.backend = (MappingStage(self.config.mapping, self.config.threaded, self.config.queue_size,
                                     self.config.device, self.timings) if self.config.mapping.enabled else None)
        if self.backend is not None:
            self.backend.on_keyframe_built = self._keyframe_depth_built
        self.counters: dict[str, float] = {"frames": 0, "frames_tracked": 0, "frames_registered_later": 0,
                                           "keyframes": 0, "loops": 0,
                                           "frontend_seconds": 0.0,
                                           "wall_seconds": 0.0, "path_given": 0.0, "path_tracked": 0.0}
        self._frame_size: tuple[int, int] | None = None
        self._finished = False
        self.model_id: str | None = None
        self.model = None
        self.tracker = None
        self.bag = None
        self.loop_closer: LoopCloser | None = None
        self.depth_points: DepthKeyframePoints | None = None
        self.depth_source: str | None = None  # "sensor", "mvs" or "model": where keyframe surfels come from
        self.keyframe_depth: KeyframeDepth | None = None
        self._loop_after_depth: set[int] = set()  # keyframes whose loop query waits for their multi-view depth
        self._started: float | None = None
        self._pending_jobs: list[tuple[KeyframeJob, bool]] = []
        self._with_depth = False
        self._wall_offset = 0.0  # wall time of the run before a restore
        self._previous_poses: tuple[np.ndarray, np.ndarray] | None = None
        self._last_frame: tuple[Frame, bool] | None = None  # the newest frame and whether tracking held
        self._restart_seam = False  # the next keyframe's odometry edge crosses the seam of a restarted map
        # (the `initialized` event of a new map, its frames' poses): applied once the map's first keyframe is in
        self._revise_on_keyframe: tuple[dict[str, Any], dict[int, np.ndarray]] | None = None
        self.last_frame_mapped: int | None = None  # the final frame's index when finish() mapped it too
        # Frames pushed while the device poses are judged (pose_mode auto without depth): tracked by the device only
        # and kept; the chosen source goes through them again from the first at the verdict (`_judge_frame`).
        self._judged: list[Frame] = []
        # events of finish() (no frame result carries them): a decision on the device poses, loops
        self.finish_events: list[dict[str, Any]] = []
        self.finish_status = FinishStatus()  # finish()'s phase and progress, for progress bars and messages
        self.depth_registration = DepthRegistration(self.config.input.depth_camera,
                                                    self.config.input.detect_misregistration_frames)

    # ------------------------------------------------------------------------------------------------ public API
    @property
    def revision(self) -> int:
        """The trajectory revision: grows each time a loop closure rewrites past poses."""
        return self._traj.revision

    @property
    def model_intrinsics(self) -> Intrinsics | None:
        """The camera at model resolution (given or estimated), when the model runs."""
        return None if self._model is None else self._model.model_intrinsics

    @property
    def num_gaussians(self) -> int:
        return 0 if self.backend is None else self.backend.num_gaussians()

    @property
    def pose_source(self):
        """The session's pose source (the tracking stage's)."""
        return self.tracking_stage.pose_source

    @property
    def needs_every_frame(self) -> bool:
        """Whether a live stream should skip no frame now: while device poses are judged over the first frames
        (their triples need the frames as the camera took them; skipped ones would make a different verdict)."""
        return bool(getattr(self.pose_source, "judging", False))

    @property
    def selector(self) -> MotionKeyframeSelector:
        return self.tracking_stage.selector

    @property
    def pose_graph(self) -> Sim3PoseGraph:
        """The keyframe pose graph (the loop-closing stage's: read it only while that stage is idle)."""
        return self.loop_stage.pose_graph

    def push(self, frame: Frame) -> FrameResult:
        """Track one frame (and queue its keyframe for mapping); returns its pose and events."""
        if self._finished:
            raise ValueError("this SLAM session is finished; start a new one")
        if not isinstance(frame, Frame):
            raise ValueError(f"push() takes a worker.data.Frame, got {type(frame).__name__}")
        self._raise_if_a_stage_failed()
        start = time.perf_counter()
        self._started = self._started or start
        frame, registration_events = self.depth_registration.apply(frame, self.frame_intrinsics(frame))
        self._check_frame(frame)
        result = self._push_frame(frame)
        result.events += registration_events
        self.counters["frames"] += 1
        self.counters["frontend_seconds"] += time.perf_counter() - start
        self.counters["wall_seconds"] = self._wall_offset + time.perf_counter() - self._started
        return result

    def finish(self) -> None:
        """Drain the stages (every keyframe mapped, every loop query answered, the corrections applied), run the
        final refinement, stop the stages' threads."""
        if self._finished:
            return
        started = time.perf_counter()
        if self._judged:  # the stream ended while the device poses were judged: decide on what was measured
            decision = self.pose_source.conclude(self._judged[-1].index)
            self.finish_events += self._replay_judged(decision).events
        status = self.finish_status
        if self.backend is not None:
            self._map_last_frame()
            self._queue_depth_jobs(force=True)
            self._flush_map_jobs(force=True)
            backlog = self.backend.pending
            status.begin("mapping", backlog, done=lambda: backlog - self.backend.pending)
            self.backend.wait_idle()
        status.begin("loop_closing", self.loop_stage.pending)
        self.loop_stage.wait_idle()
        self.finish_events += self._apply_corrections()  # loops the stage closed after the last frame
        if self.finish_events and self.backend is not None:
            self.backend.wait_idle()
        if self.backend is not None:
            if self.config.mapping.final_refine_passes:
                budget = self.config.mapping.final_refine_budget_s  # from the start of finish() (the drain too)
                since = started if self.config.mapping.final_refine_budget_counts_drain else time.perf_counter()
                left = None if not budget else max(0.0, budget - (time.perf_counter() - since))
                passes = self.config.mapping.final_refine_passes
                status.begin("refining", passes * self.backend.map.held_images,
                             deadline=None if left is None else time.perf_counter() + left)
                moved = self.backend.refine_all(passes, budget_s=left, seed=self.config.mapping.final_refine_seed,
                                                train_poses=self._refines_keyframe_poses(), on_step=status.step)
                if moved:
                    self.finish_events.append(self._follow_refined_keyframes(moved))
        status.begin("done", 0)
        self.close()
        if self._started is not None:
            self.counters["wall_seconds"] = self._wall_offset + time.perf_counter() - self._started
        self._finished = True

    def _refines_keyframe_poses(self) -> bool:
        """Whether the final refinement refines the keyframes' cameras: asked for, and the poses are not the
        device's own to keep (pose_mode fixed)."""
        return self.config.mapping.final_refine_poses and self.pose_source_choice()["pose_source"] != "fixed"

    def _follow_refined_keyframes(self, motions: dict[int, np.ndarray]) -> dict[str, Any]:
        """Move the trajectory's keyframes by the final refinement's world-frame motions (keyframes the map did not
        hold follow the newest refined one before them) and each frame with the keyframes before and after it.
        Returns the event."""
        trajectory = self.tracking_stage.trajectory
        old = {k: pose.copy() for k, pose in trajectory.keyframe_poses.items()}
        _, changed = self.tracking_stage.apply_correction(
            {k: motion @ old[k] for k, motion in motions.items() if k in old})
        revision = trajectory.spread_keyframe_moves(old)
        return {"type": "poses_refined", "keyframes": len(changed), "revision": revision}

    def close(self) -> None:
        """Stop the stages' threads without further work (idempotent)."""
        if self.backend is not None:
            self.backend.close()
        self.loop_stage.close()

    def _raise_if_a_stage_failed(self) -> None:
        if self.backend is not None:
            self.backend.raise_if_failed()
        self.loop_stage.raise_if_failed()

    def trajectory(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]:
        """[(index, timestamp, c2w pose 4x4)] of "all" frames or the "keyframes", at the current revision."""
        return self._traj.listing(which)

    def render_view(self, pose_c2w: np.ndarray, K: np.ndarray | torch.Tensor, width: int, height: int,
                    as_captured_at: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render the map: (rgb uint8 [h,w,3], depth float32 [h,w]) seen from c2w `pose_c2w` with intrinsics K, in
        the map's exposure-normalised colours or, with `as_captured_at` (a frame index), under the exposure the
        camera had at that frame (interpolated between its keyframes: what the photo of that frame shows)."""
        if self.backend is None:
            raise ValueError("mapping is disabled in this session's config")
        pose = np.asarray(pose_c2w, np.float64)
        Km = torch.as_tensor(np.asarray(K, np.float64), dtype=torch.float32)
        if pose.shape != (4, 4) or tuple(Km.shape) != (3, 3):
            raise ValueError("render_view needs a 4x4 pose and a 3x3 K")
        if not (0 < width <= 8192 and 0 < height <= 8192):
            raise ValueError(f"render size must be within 1..8192, got {width}x{height}")
        out = self.backend.render(pose, Km, int(width), int(height), as_captured_at)
        rgb = (out.rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return rgb, out.depth.to(torch.float32).cpu().numpy()

    def export_ply(self) -> bytes:
        """The map as a binary PLY (3DGS/2DGS layout)."""
        if self.backend is None:
            raise ValueError("mapping is disabled in this session's config")
        return self.backend.to_ply_bytes()

    def stats(self) -> dict[str, Any]:
        """Counters for status pages and metrics."""
        frames = self.counters["frames"]
        wall = self.counters["wall_seconds"]
        return {**self.counters, "revision": self.revision, "mode": self.mode,
                "num_gaussians": self.num_gaussians, "fps": frames / wall if wall > 0 else 0.0,
                "backend_pending": 0 if self.backend is None else self.backend.pending,
                "backend_seconds": 0.0 if self.backend is None else self.backend.busy_seconds,
                **self.live_stats(), "pose_source": self.pose_source_choice()["pose_source"],
                "runtime_breakdown": self.timings.breakdown(int(frames))}

    def pose_source_choice(self) -> dict[str, Any]:
        """How the session uses the frames' device poses: `pose_source` (prior, fixed or seeded; None when it does
        not use them) and, for `pose_mode` auto without depth, whether it was judged yet and the agreement figures
        it was chosen by (`worker.tracking.pose_choice`)."""
        if self.tracking != "device":
            return {"pose_source": None, "pose_agreement": None}
        summary = getattr(self.pose_source, "summary", None)
        if summary is not None:
            return summary()
        pose_mode = self.config.input.pose_mode
        return {"pose_source": "seeded" if pose_mode == "auto" else pose_mode, "pose_agreement": None}

    def live_stats(self) -> dict[str, Any]:
        """What a live client watches, cheap to read while frames stream: how far mapping lags (keyframes waiting,
        seconds the oldest has waited), what it shed, what it still owes and caught up since (refinement made up
        while idle), and the loop-closing stage's backlog."""
        mapping = {"mapping_lag_keyframes": 0, "mapping_lag_s": 0.0, "keyframes_shed": {}, "keyframes_owed": 0,
                   "keyframes_caught_up": 0} if self.backend is None else self.backend.stats()
        return {**{key: mapping[key] for key in ("mapping_lag_keyframes", "mapping_lag_s", "keyframes_shed",
                                                 "keyframes_owed", "keyframes_caught_up")},
                "loop_pending": self.loop_stage.pending}

    # ------------------------------------------------------------------------------------------------- helpers
    def _new_loop_stage(self, pose_graph: Sim3PoseGraph, closer: LoopCloser | None,
                        depth_points: DepthKeyframePoints | None) -> LoopClosingStage:
        """The loop-closing stage; inline with the learned model, whose tracker state loop closure reads."""
        threaded = self.config.threaded and self.tracking != "model"
        device_poses = self.config.input.device_poses
        solve_priors_every = (device_poses.graph_solve_keyframes if device_poses.drift_correction == "pose_graph"
                              and self.tracking == "device" and not self._with_depth else 0)
        return LoopClosingStage(self.config.loop, pose_graph, closer, depth_points, metric=self._metric_loops(),
                                threaded=threaded, timings=self.timings, solve_priors_every=solve_priors_every)

    def _new_pose_graph(self, metric: bool = False) -> Sim3PoseGraph:
        """The keyframe pose graph; `metric` (given poses and depth) leaves the scale no freedom."""
        lc = self.config.loop
        sigmas = {kind: EdgeSigmas(s.rotation, s.translation, METRIC_LOG_SCALE_SIGMA if metric else s.log_scale)
                  for kind, s in {**DEFAULT_SIGMAS, "loop": EdgeSigmas(0.02, 0.02, 0.02)}.items()}
        return Sim3PoseGraph(robust=None if lc.robust_kernel == "none" else lc.robust_kernel, robust_k=lc.robust_k,
                             sigmas=sigmas)

    def _check_frame(self, frame: Frame) -> None:
        size = (frame.width, frame.height)
        if self._frame_size is None:
            posed = frame.pose is not None and self.config.input.pose_mode != "ignore"
            with_depth = self._uses_depth(frame)
            tracking = choose_tracking(self.config.frontend.tracking, frame, posed, with_depth,
                                       self._custom_model())
            self._frame_size = size
            self._with_depth = with_depth
            self._setup(tracking, with_depth=with_depth)
        elif size != self._frame_size:
            raise ValueError(f"frame {frame.index} is {size[0]}x{size[1]}, the session's frames are "
                             f"{self._frame_size[0]}x{self._frame_size[1]}")
        if self.tracking == "rgbd_odometry" and frame.depth is None:
            raise ValueError(f"frame {frame.index} has no depth, but this session tracks by RGB-D odometry")

    def _custom_model(self) -> bool:
        """Whether the configured model is the user's (weights other than the shipped synthetic ones)."""
        fc = self.config.frontend
        return bool(fc.checkpoint) or fc.model != "tiny"

    def frame_intrinsics(self, frame: Frame) -> Intrinsics | None:
        """The frame's camera: its own intrinsics, else the session's (rescaled to the frame size)."""
        if frame.intrinsics is not None:
            return frame.intrinsics
        if self.intrinsics is None:
            return None
        if (self.intrinsics.width, self.intrinsics.height) != (frame.width, frame.height):
            return self.intrinsics.scaled(frame.width, frame.height)
        return self.intrinsics

    def _uses_depth(self, frame: Frame) -> bool:
        return frame.depth is not None and self.config.input.use_depth

    # ---------------------------------------------------------------------------------------------- frame path
    def _push_frame(self, frame: Frame) -> FrameResult:
        """Pose source -> keyframe selection -> map job -> loop closure, the same for every source."""
        if self.needs_every_frame:
            return self._judge_frame(frame)
        return self._track_and_map(frame)

    def _judge_frame(self, frame: Frame) -> FrameResult:
        """A frame while the device poses are judged: its pose is the device's (provisional), it is kept, and no
        keyframe is made. At the verdict every kept frame goes through the chosen source from the first, as if the
        session had begun with it: with `seeded`, the map never holds a keyframe on the device poses the images
        disagreed with (the keyframes' multi-view depth is made on the visual odometry's poses). The verdict
        frame's result carries the replayed frames' events and the new trajectory revision."""
        tracking, pose = self.tracking_stage.track(frame, self.frame_intrinsics(frame))
        self._judged.append(frame)
        if self.needs_every_frame:
            return FrameResult(frame.index, frame.timestamp, pose, False, tracking.submap_id, self.revision,
                               [dict(e) for e in tracking.events], tracked=tracking.tracked)
        return self._replay_judged(tracking.events)

    def _replay_judged(self, decision: list[dict[str, Any]]) -> FrameResult:
        """The judged frames through the chosen source, from the first; the last one's result, carrying the
        decision's `pose_source_chosen` event (with the frames replayed and the new revision) and the replayed
        frames' events."""
        judged, self._judged = self._judged, []
        # No keyframe has a multi-view depth yet to measure motion against: the judging's triangulated points do
        self.tracking_stage.selector.set_scene_depth(getattr(self.pose_source, "scene_depth", None))
        events: list[dict[str, Any]] = []
        for kept in judged:
            result = self._track_and_map(kept)
            events += result.events
        revision = self._traj.revise_frames({})  # the provisional poses of the judged frames are replaced
        chosen = [{**e, "frames_replayed": len(judged), "revision": revision}
                  for e in decision if e.get("type") == "pose_source_chosen"]
        result.events = chosen + [dict(e) for e in decision if e.get("type") != "pose_source_chosen"] + events
        result.revision = revision
        return result

    def _track_and_map(self, frame: Frame) -> FrameResult:
        """One frame through the chosen pose source, the keyframe decision, mapping and loop closure."""
        intrinsics = self.frame_intrinsics(frame)
        events = self._apply_corrections()
        tracking, pose = self.tracking_stage.track(frame, intrinsics)
        events += [self._apply_tracking_event(event) for event in tracking.events if event.get("type") != "maps_merged"]
        self._restart_seam |= any(e.get("type") == "relocalized" and e.get("method") == "reinitialized"
                                  for e in tracking.events)
        prediction = tracking.prediction
        if prediction is None and self._model is not None:  # the model predicts the surfels beside the source
            with self.timings.measure("frontend_inference"):
                prediction = self._model.predict(frame, intrinsics)
            self._accumulate_path(pose, prediction[1].pose_world.numpy())
        self.counters["frames_tracked"] += int(tracking.tracked)
        if self.keyframe_depth is not None and tracking.tracked:  # a lost frame's held pose is not its own
            self.keyframe_depth.add_frame(frame.index, frame.image)
        is_kf = self.tracking_stage.is_keyframe(tracking, pose, *self._scene_view(frame, tracking))
        if is_kf:
            self.tracking_stage.add_keyframe(frame, pose, submap_id=tracking.submap_id,
                                             edge_kind="restart" if self._restart_seam else None)
            self._restart_seam = False
            self.counters["keyframes"] += 1
            if self.keyframe_depth is not None:  # mapped once later frames give it neighbours
                self.keyframe_depth.add_keyframe(frame.index, self.camera(frame).matrix().numpy(), tracking.depth)
            elif self.backend is not None:  # the keyframe enters the map before a loop closure can move it
                self._pending_jobs.append(self._keyframe_job(frame, prediction))
                self._flush_map_jobs()
            if self.loop_closer is not None:
                events += self._keyframe_loop(frame, prediction)
        if self._revise_on_keyframe is not None:
            self._revise_new_map_frames(frame.index if is_kf else None, tracking.submap_id)
        for event in tracking.events:
            if event.get("type") == "maps_merged" and self.tracking_stage.last_keyframe is not None:
                self._submit_map_join(pose, event)
        world = self.tracking_stage.add_frame(frame, pose, is_kf, tracking.submap_id)
        self._last_frame = None if is_kf else (frame, tracking.tracked)
        if self.backend is not None:
            self._queue_depth_jobs()
            self._flush_map_jobs()
        return FrameResult(frame.index, frame.timestamp, world, is_kf, tracking.submap_id, self.revision, events,
                           tracked=tracking.tracked)

    def _scene_view(self, frame: Frame, tracking) -> tuple[np.ndarray | None, Intrinsics | None]:
        """The depth the keyframe selector measures motion against, and the frame's camera: the source's depth
        (sensor, or the points it triangulated), else the frame's sensor depth; without either (posed RGB), the
        selector gets the median depth of the newest keyframe multi-view stereo has estimated."""
        depth = tracking.depth if tracking.depth is not None else (frame.depth if self._with_depth else None)
        if depth is None and self.keyframe_depth is not None:
            self.tracking_stage.selector.set_scene_depth(self.keyframe_depth.recent_hint[1])
        camera = self.frame_intrinsics(frame) or self.tracking_stage.source_intrinsics(frame.width, frame.height)
        return depth, camera

    def _apply_tracking_event(self, event: dict[str, Any]) -> dict[str, Any]:
        """Act on a pose source's event; returns it as clients get it. `initialized` (monocular odometry) carries
        the re-estimated poses of the frames it waited for: they replace the placeholders (a new revision)."""
        if event.get("type") != "initialized" or not event.get("frames"):
            return dict(event)
        poses = {int(i): np.asarray(p, np.float64) for i, p in event["frames"]}
        revised = {i: p for i, p in poses.items() if np.all(np.isfinite(p))}
        if event.get("intrinsics") and self.depth_points is not None:  # keyframe points made with the old camera
            self.loop_stage.submit(CameraUpdate(Intrinsics.from_dict(event["intrinsics"]).matrix()))
        out = {k: v for k, v in event.items() if k != "frames"}
        if int(event.get("map", 1)) > 1:  # a new map's waiting frames: tied to its first keyframe (_push_frame)
            self._revise_on_keyframe = (out, revised)
            return out
        out["revision"] = self._traj.revise_frames(revised)
        out["frames_revised"] = len(revised)
        return out

    def _revise_new_map_frames(self, keyframe: int | None, submap_id: int) -> None:
        """The frames a new map waited for (reported lost), posed by its initialisation: tied to the map's first
        keyframe, so that a loop or a join that moves the map moves them too (a new revision, said in the
        `initialized` event with the frames' indices)."""
        out, revised = self._revise_on_keyframe
        self._revise_on_keyframe = None
        out["revision"] = self._traj.revise_frames(revised, keyframe=keyframe, submap_id=submap_id)
        out["frames_revised"] = len(revised)
        out["registered_frames"] = sorted(revised)
        self.counters["frames_registered_later"] += len(revised)

    def _submit_map_join(self, pose: np.ndarray, event: dict[str, Any]) -> None:
        """The Sim(3) edge of a pose source's `maps_merged` event (`relative`: this frame, tracked at `pose`, in
        the frame of the older frame `place`), moved onto the keyframes those frames follow, to the loop stage;
        its pose-graph solve comes back as a correction with the `maps_merged` event."""
        traj, place = self._traj, int(event["place"])
        if place in traj.tracked_keyframe_poses:
            i, before = place, np.eye(4)
        else:
            record = next((r for r in reversed(traj.frames) if r.index == place), None)
            if record is None:
                return
            i, before = record.keyframe, record.relative  # T_i^-1 T_place, as tracked
        j = self.tracking_stage.last_keyframe
        after = sim3_inverse(torch.from_numpy(traj.tracked_keyframe_poses[j])).numpy() @ pose  # T_j^-1 T_frame
        relative = before @ np.asarray(event["relative"], np.float64) @ sim3_inverse(torch.from_numpy(after)).numpy()
        self.loop_stage.submit(MapJoin(i, j, relative, event))

    def _map_last_frame(self) -> None:
        """At the end of a session the newest view enters the map too (when it is not a keyframe already and was
        tracked): it is the view a user looks at first. Keyframe-like surfels from its depth, sensor or multi-view;
        not a pose-graph node (nothing moves it any more)."""
        if self._last_frame is None or self.depth_source == "model":
            return
        frame, tracked = self._last_frame
        self._last_frame = None
        sensor = self.depth_source == "sensor"
        if not tracked or (sensor and (frame.depth is None or self.config.input.surfel_init != "depth")):
            return
        pose = self._traj.pose_at(frame.index)
        if self.keyframe_depth is not None:
            self.keyframe_depth.add_keyframe(frame.index, self.camera(frame).matrix().numpy(), None)
        else:
            self._pending_jobs.append((self._depth_job(frame, pose), False))
        self.last_frame_mapped = frame.index

    def camera(self, frame: Frame) -> Intrinsics:
        """The frame's camera: given, else the pose source's estimate."""
        intrinsics = self.frame_intrinsics(frame) or self.tracking_stage.source_intrinsics(frame.width, frame.height)
        if intrinsics is None:
            raise ValueError("no intrinsics for this session: give them with the frames or the session")
        return intrinsics

    def _queue_depth_jobs(self, force: bool = False) -> None:
        """Multi-view depth jobs of the keyframes that have their neighbours now (all of them when `force`)."""
        if self.keyframe_depth is None:
            return
        for job in self.keyframe_depth.ready_jobs(self._traj.pose_at, force):
            self._pending_jobs.append((job, False))

    def _keyframe_loop(self, frame: Frame, prediction) -> list[dict[str, Any]]:
        """Queue loop closure for a new keyframe: against keyframe depth (ORB + PnP + ICP) or the model's hidden
        states. With multi-view depth the mapping stage queues it once it has built the keyframe's depth."""
        if self.keyframe_depth is not None:
            self._loop_after_depth.add(frame.index)
        elif self.depth_points is not None:
            intr = self.camera(frame)
            image = torch.from_numpy(frame.image).permute(2, 0, 1)[None].float() / 255.0
            self.loop_stage.submit(LoopQuery(frame.index, image, intr, torch.from_numpy(
                np.asarray(frame.depth, np.float32)), intr.matrix()))
        else:
            self.loop_stage.submit(LoopQuery(frame.index, prediction[0].tensor, self.model_intrinsics))
        return self._apply_corrections() if not self.loop_stage.pending else []

    def _keyframe_depth_built(self, job: KeyframeJob) -> None:
        """The mapping stage built a keyframe's multi-view depth (in its thread): queue its loop query."""
        if job.kf_id not in self._loop_after_depth or job.depth is None:
            return
        self._loop_after_depth.discard(job.kf_id)
        h, w = job.image.shape[:2]
        self.loop_stage.submit(LoopQuery(job.kf_id, job.image.permute(2, 0, 1)[None],
                                         Intrinsics.from_matrix(job.K, w, h), job.depth, job.K))

    def _accumulate_path(self, given: np.ndarray, tracked: np.ndarray) -> None:
        """Path lengths of the given and the tracked trajectories: their ratio converts model units to pose units."""
        if self._previous_poses is not None:
            g0, t0 = self._previous_poses
            self.counters["path_given"] += float(np.linalg.norm(given[:3, 3] - g0[:3, 3]))
            self.counters["path_tracked"] += float(np.linalg.norm(tracked[:3, 3] - t0[:3, 3]))
        self._previous_poses = (given.copy(), tracked.copy())

    def _flush_map_jobs(self, force: bool = False) -> None:
        """Submit keyframe jobs; model-unit surfels wait until the path gives their scale, and every job while the
        pose source is still estimating the camera (unless `force`)."""
        if getattr(self.pose_source, "calibrating", False) and not force:
            return
        while self._pending_jobs:
            job, needs_scale = self._pending_jobs[0]
            if needs_scale:
                tracked_path = self.counters["path_tracked"]
                if tracked_path < 1e-9 and not force:
                    return
                scale = self.counters["path_given"] / tracked_path if tracked_path >= 1e-9 else 1.0
                job.grid = {**job.grid, "means": job.grid["means"] * scale, "scales": job.grid["scales"] * scale}
            self._pending_jobs.pop(0)
            self.backend.submit(job)

    def _depth_job(self, frame: Frame, pose: np.ndarray) -> KeyframeJob:
        """A map job with surfels from the frame's own depth; built in the backend with the camera known then (a
        session without intrinsics holds its jobs until the focal length is estimated)."""
        image = torch.from_numpy(frame.image).to(torch.float32) / 255.0
        depth = torch.from_numpy(np.asarray(frame.depth, np.float32))

        def build() -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
            K = self.camera(frame).matrix()
            return K, grid_from_depth(image, depth, K), depth

        return KeyframeJob(frame.index, pose, None, image, {}, depth, build=build)

    def _keyframe_job(self, frame: Frame, prediction) -> tuple[KeyframeJob, bool]:
        """(the keyframe's map job, whether its surfels are still in model units): surfels from the frame's depth,
        else from the model's prediction."""
        world_pose = self._traj.keyframe_poses[frame.index]
        if self._uses_depth(frame) and self.config.input.surfel_init == "depth" and self._metric_poses():
            return self._depth_job(frame, world_pose), False
        prep, tracked = prediction
        grid, depth = self._prediction_grid(frame, prep, tracked.surfels)
        image = prep.tensor[0].permute(1, 2, 0).contiguous()
        job = KeyframeJob(frame.index, world_pose, self.model_intrinsics.matrix(), image, grid, depth)
        # The model's own poses are in its units; next to another source its surfels wait for the path ratio.
        return job, depth is None and self.tracking != "model"

    # ------------------------------------------------------------------------------------------------- set-up
    def _setup(self, tracking: str, with_depth: bool) -> None:
        """Build what the pose source needs: the source itself, the model and tracker (model tracking, or surfels
        without depth-initialised ones), the bag of hidden states and the loop closer."""
        self.tracking = tracking
        self.mode = MODE_OF_TRACKING[tracking]
        cfg = self.config
        self.depth_source = self._choose_depth_source(tracking, with_depth)
        mvs = self.depth_source == "mvs" and cfg.mapping.enabled
        needs_model = tracking == "model" or self.depth_source == "model" or (
            with_depth and cfg.input.surfel_init == "model")
        if needs_model:
            self._build_frontend()
        if mvs:
            fill = self._model_depth_filler() if cfg.input.mvs_fill == "model" else None
            self.keyframe_depth = KeyframeDepth(cfg.depth, cfg.input.mvs_buffer_frames, cfg.input.mvs_frames_after,
                                                fill, propagate=cfg.input.mvs_fill == "propagate",
                                                planes=PlaneSettings() if cfg.input.mvs_planes else None,
                                                borders=BorderSettings() if cfg.input.mvs_border_planes else None)
            if self.backend is not None:
                self.backend.use_multiview_depth()
        self.tracking_stage.pose_source = self._build_pose_source(tracking)
        self.tracking_stage.timing_stage = "frontend_inference" if tracking == "model" else "frontend_tracking"
        log.info("session tracking: %s (mode %s), surfels from %s", tracking, self.mode, self.depth_source)
        self._build_loop_closer(tracking, with_depth)
        self.loop_stage.close()
        self.loop_stage = self._new_loop_stage(self._new_pose_graph(metric=self._metric_loops()),
                                               self.loop_closer, self.depth_points)

    def _build_loop_closer(self, tracking: str, with_depth: bool) -> None:
        """The loop closer and the keyframe points it verifies with, when this session closes loops."""
        cfg = self.config
        loops = cfg.loop.enabled and not (tracking == "device" and cfg.input.pose_mode == "fixed")
        if not loops:
            return
        if tracking != "model":
            if not with_depth and self.keyframe_depth is None:
                log.warning("%s without depth: loop closure is off (no points to relocalize with)", tracking)
                return
            self.depth_points = DepthKeyframePoints()
            self.loop_closer = LoopCloser(cfg.loop, model=self.model, depth_points=self.depth_points,
                                          timings=self.timings)
        else:
            self.loop_closer = LoopCloser(cfg.loop, model=self.model, tracker=self.tracker, bag=self.bag,
                                          timings=self.timings)

    def _load_model(self):
        """The configured checkpoint, else a seeded random model (with a warning); sets `model_id`."""
        from worker.frontend import build_model
        from worker.frontend.checkpoint import load_checkpoint

        fc = self.config.frontend
        path = self.config.checkpoint_path()
        if path is not None:
            self.model_id = f"checkpoint:{path.name}"
            return load_checkpoint(path, device=self.config.device)
        log.warning("no checkpoint for model %r: using a randomly initialised model (seed %d); poses and maps "
                    "will be meaningless until trained weights are given", fc.model, fc.seed)
        with torch.random.fork_rng():
            torch.manual_seed(fc.seed)
            model = build_model(fc.model, device=self.config.device)
        self.model_id = f"random:{fc.model}:seed={fc.seed}"
        return model

    def _build_frontend(self) -> None:
        from worker.frontend.tracker import SubmapTracker, TrackerConfig
        from worker.loop.bag import HiddenStateBag

        fc = self.config.frontend
        self.model = self._load_model()
        self.tracker = SubmapTracker(self.model, TrackerConfig(
            submap_length=fc.submap_size, keyframe_translation=fc.keyframe_depth_ratio,
            keyframe_rotation_deg=fc.keyframe_rotation_deg))
        self.bag = HiddenStateBag()
        self._model = ModelTracking(self.tracker, self.bag, fc.long_side, self._estimate_intrinsics)

    def _choose_depth_source(self, tracking: str, with_depth: bool) -> str:
        """Where keyframe surfels come from: the frames' depth, else multi-view stereo on the tracked poses, or
        the model (when it tracks, or when the config asks for it)."""
        if with_depth:
            return "sensor"
        requested = self.config.input.depth_source
        if requested == "auto":
            return "model" if tracking == "model" else "mvs"
        return requested

    def _model_depth_filler(self):
        """The learned model's single-view depth (worker.engine.model_depth), loaded like the tracker's model."""
        from worker.engine.model_depth import ModelDepth

        if self.model is None:
            self.model = self._load_model()
        return ModelDepth(self.model, self.config.frontend.long_side).depth

    def _build_pose_source(self, tracking: str):
        pose_mode = self.config.input.pose_mode
        if tracking == "device" and (pose_mode == "seeded" or (pose_mode == "auto" and self._with_depth)):
            from worker.tracking.seeded import seeded_tracking

            return seeded_tracking(self.config, self._with_depth, lambda prior: self.loop_stage.submit(prior))
        if tracking == "device" and pose_mode == "auto":
            from worker.tracking.pose_choice import ChosenDevicePoses
            from worker.tracking.seeded import seeded_tracking

            return ChosenDevicePoses(lambda: seeded_tracking(self.config, False,
                                                             lambda prior: self.loop_stage.submit(prior)),
                                     self.config.input.pose_choice)
        if tracking == "device":
            return DevicePoses()
        if tracking == "model":
            return self._model
        if tracking == "rgbd_odometry":
            from worker.tracking.rgbd_odometry import RgbdOdometry

            return RgbdOdometry(self.config.tracking.rgbd)
        from worker.tracking.visual_odometry import VisualOdometry

        return VisualOdometry(self.config.tracking.visual)

    # ------------------------------------------------------------------------------------------- the model
    def _estimate_intrinsics(self, surfels, prep) -> Intrinsics:
        from worker.frontend.focal import estimate_focal, intrinsics_from_focal

        h, w = prep.tensor.shape[-2:]
        focal = estimate_focal(surfels.points.float(), surfels.conf.float())
        intr = intrinsics_from_focal(focal, w, h)
        log.info("estimated focal length %.1f px at %dx%d", focal, w, h)
        return intr

    def estimated_intrinsics(self) -> Intrinsics | None:
        """The camera at the input frames' resolution: given, else the pose source's estimate (visual odometry's
        self-calibration, RGB-D odometry's guess), else the model's (from its points)."""
        if self.intrinsics is not None and self._frame_size is not None and (
                self.intrinsics.width, self.intrinsics.height) != tuple(self._frame_size):
            return self.intrinsics.scaled(*self._frame_size)  # frames worked on smaller than the camera given
        if self.intrinsics is not None or self._frame_size is None:
            return self.intrinsics
        from_source = self.tracking_stage.source_intrinsics(*self._frame_size)
        if from_source is not None:
            return from_source
        if self.model_intrinsics is None:
            return None
        return _uncrop_intrinsics(self.model_intrinsics, self._prep_geometry(), *self._frame_size)

    def _prep_geometry(self) -> tuple[float, tuple[int, int, int, int]]:
        from worker.frontend.preprocess import centre_crop_box, resized_size

        w, h = self._frame_size
        new_w, new_h = resized_size(w, h, self.config.frontend.long_side)
        return new_w / w, centre_crop_box(new_w, new_h)

    def _model_depth(self, frame: Frame, prep) -> torch.Tensor | None:
        """The frame's depth at model resolution (nearest neighbour, then the same crop), or None."""
        if not self._uses_depth(frame):
            return None
        import cv2

        h, w = frame.depth.shape
        new_w, new_h = round(w * prep.scale), round(h * prep.scale)
        depth = cv2.resize(np.asarray(frame.depth, np.float32), (new_w, new_h), interpolation=cv2.INTER_NEAREST)
        left, top, cw, ch = prep.crop
        return torch.from_numpy(np.ascontiguousarray(depth[top:top + ch, left:left + cw]))

    def _prediction_grid(self, frame: Frame, prep, surfels) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
        """A keyframe's surfel grid from the model; with depth, means from the depth brought to the tracker's
        units (the median ratio of predicted to measured depth), so the map stays consistent with the poses."""
        depth = self._model_depth(frame, prep)
        if depth is not None and self.tracking in ("model", "visual_odometry"):  # pose units are not metric
            valid = (depth > 0) & (surfels.points[..., 2] > 0)
            if bool(valid.any()):
                depth = depth * float((surfels.points[..., 2][valid].float() / depth[valid]).median())
        K = self.model_intrinsics.matrix()
        fc = self.config.frontend
        grid = grid_from_prediction(surfels.points.float(), surfels.conf.float(), surfels.quats.float(),
                                    surfels.scales.float(), surfels.opacity.float(), surfels.colors.float(),
                                    fc.min_confidence, depth=depth, K=K, min_kept_fraction=fc.min_kept_fraction,
                                    ray_aligned=fc.ray_aligned_surfels)
        return grid, depth

    # ------------------------------------------------------------------------------------------ loop closure
    def _metric_poses(self) -> bool:
        """Whether poses are in the depth's units (given poses, or tracked on the depth itself)."""
        return self.tracking in ("device", "rgbd_odometry")

    def _metric_loops(self) -> bool:
        return self._metric_poses() and self._with_depth

    def _apply_corrections(self) -> list[dict[str, Any]]:
        """Apply the loop-closing stage's new corrections (in order); returns their loop events."""
        return [self._apply_correction(c) for c in self.loop_stage.take_corrections()]

    def _apply_correction(self, correction: LoopCorrection) -> dict[str, Any]:
        """Move the trajectory and the map to the optimised keyframe poses. Keyframes made after the optimisation
        follow the newest optimised keyframe before them, so nothing jumps. Returns the loop event."""
        revision, changed = self.tracking_stage.apply_correction(correction.poses)
        if self.backend is not None:
            for job, _ in self._pending_jobs:  # not in the map yet (waiting for their scale): they move here
                if job.kf_id in changed:
                    job.pose = changed.pop(job.kf_id)
            for waiting in [] if self.keyframe_depth is None else self.keyframe_depth.pending:
                changed.pop(waiting.kf_id, None)  # their jobs are made later, at the then current pose
            if changed:
                self.backend.submit(PoseUpdateJob(changed))
        counter = {"maps_merged": "maps_merged", "drift_corrected": "drift_corrections"}.get(
            correction.event.get("type"), "loops")
        self.counters[counter] = self.counters.get(counter, 0) + 1
        return {**correction.event, "revision": revision}

    # ---------------------------------------------------------------------------------------- snapshot/restore
    def snapshot(self) -> bytes:
        """Everything needed to continue this session, as msgpack bytes (waits for the stages' parts)."""
        return self.begin_snapshot().result()

    def begin_snapshot(self, stored_chunks: Mapping[int, int] | None = None) -> SnapshotFuture:
        """A snapshot of the session as of now, without waiting: the tracking state is packed at once, the map and
        the loop-closing state by their stages once they have done what was submitted before (see the module
        docstring); `result()` gives the bytes that `restore` takes. With `stored_chunks` (chunk -> version already
        stored) the snapshot is incremental: the trajectory's sealed frame records and every large array (keyframe
        images, depth, the map's tensors) stay out of the bytes, and `future.chunks` (a ChunkWrite) holds the chunks
        not stored yet and the arrays by digest, for `restore(data, chunks)`."""
        if self.backend is not None:
            self._flush_map_jobs(force=True)
        trajectory, chunks = (None, None) if stored_chunks is None else self._traj.chunked_state(stored_chunks)
        arrays = None if chunks is None else chunks.arrays
        # packed now: the next frames change what it refers to
        tracking = pack(self._tracking_state(trajectory), external=arrays)
        backend, loop_stage = self.backend, self.loop_stage
        parts = ["loop"] + ([] if backend is None else ["map"])
        future = SnapshotFuture(parts, lambda done: pack({"format": SNAPSHOT_FORMAT, "tracking": tracking,
                                                          "map": done.get("map"), "loop": done["loop"]}))
        if backend is not None:
            backend.at_marker(lambda: future.deliver("map", lambda: pack(backend.state_dict(), external=arrays)))
        loop_stage.at_marker(lambda: future.deliver("loop", lambda: pack(loop_stage.state_dict(), external=arrays)))
        future.chunks = chunks
        return future

    def _tracking_state(self, trajectory: dict[str, Any] | None = None) -> dict[str, Any]:
        """The tracking thread's part of a snapshot (`trajectory`: the trajectory's chunked state)."""
        return {
            "format": SNAPSHOT_FORMAT,
            "config": self.config.model_dump(mode="json"),
            "model_id": self.model_id,
            "intrinsics": None if self.intrinsics is None else self.intrinsics.to_dict(),
            "model_intrinsics": None if self.model_intrinsics is None else self.model_intrinsics.to_dict(),
            "mode": self.mode,
            "tracking": self.tracking,
            "with_depth": self._with_depth,
            "frame_size": None if self._frame_size is None else list(self._frame_size),
            "previous_poses": None if self._previous_poses is None else list(self._previous_poses),
            "counters": dict(self.counters),
            **self.tracking_stage.state_dict(trajectory),
            "tracker": None if self.tracker is None else self.tracker.state_dict(),
            "bag": None if self.bag is None else self.bag.to_bytes(torch.float32),
            "keyframe_depth": None if self.keyframe_depth is None else self.keyframe_depth.state_dict(),
            "loop_after_depth": sorted(self._loop_after_depth),
            "judged_frames": [_frame_state(f) for f in self._judged],
        }

    def _load_waiting_loops(self, state: dict[str, Any]) -> None:
        """Keyframes whose loop query waits for their multi-view depth; a format-1 snapshot lists them as
        `loops_waiting`, with the depth when the backend had built it (their queries go to the stage now)."""
        self._loop_after_depth = {int(k) for k in state.get("loop_after_depth") or []}
        for e in state.get("loops_waiting") or []:
            if e["depth"] is None:
                self._loop_after_depth.add(int(e["kf"]))
                continue
            image = torch.from_numpy(np.asarray(e["image"], np.uint8)).to(torch.float32) / 255.0
            K = torch.from_numpy(np.asarray(e["K"], np.float32))
            h, w = image.shape[:2]
            self.loop_stage.submit(LoopQuery(int(e["kf"]), image.permute(2, 0, 1)[None], Intrinsics.from_matrix(
                K, w, h), torch.from_numpy(np.asarray(e["depth"], np.float32)), K))

    @classmethod
    def restore(cls, data: bytes, chunks: Mapping[int | str, bytes] | None = None) -> SlamSystem:
        """A system continuing from `snapshot()` bytes (never unpickles anything); `chunks` holds what an
        incremental snapshot (`begin_snapshot(stored_chunks)`) left out: trajectory chunks by number, arrays by
        digest."""
        chunks = chunks or {}
        state = _flat_snapshot(unpack(data), {k: v for k, v in chunks.items() if isinstance(k, str)})
        state["trajectory"] = Trajectory.joined_state(state["trajectory"],
                                                      {k: v for k, v in chunks.items() if isinstance(k, int)})
        from worker.loop.bag import HiddenStateBag

        config = SlamConfig.from_dict(state["config"])
        intrinsics = None if state["intrinsics"] is None else Intrinsics.from_dict(state["intrinsics"])
        system = cls(config, intrinsics)
        if state["mode"] is not None:
            system._with_depth = bool(state["with_depth"])
            system._setup(state.get("tracking") or TRACKING_OF_MODE[state["mode"]], with_depth=system._with_depth)
        if system.model_id != state["model_id"]:
            raise ValueError(f"the snapshot was made with model {state['model_id']!r}, this machine has "
                             f"{system.model_id!r}")
        if state["model_intrinsics"] is not None and system._model is not None:
            system._model.model_intrinsics = Intrinsics.from_dict(state["model_intrinsics"])
        system._frame_size = None if state["frame_size"] is None else tuple(state["frame_size"])
        if state["previous_poses"] is not None:
            system._previous_poses = tuple(np.asarray(p, np.float64) for p in state["previous_poses"])
        system.counters.update(state["counters"])
        system._wall_offset = float(system.counters["wall_seconds"])
        system.tracking_stage.load_state_dict(state)
        if system.tracker is not None:
            system.tracker.load_state_dict(state["tracker"])
            system.bag = HiddenStateBag.from_bytes(state["bag"])
            if system.loop_closer is not None and system.loop_closer.pnp is None:
                system.loop_closer.relocalizer.bag = system.bag
        system.loop_stage.load_state_dict(state)
        if system.keyframe_depth is not None and state.get("keyframe_depth") is not None:
            system.keyframe_depth.load_state_dict(state["keyframe_depth"])
        system._load_waiting_loops(state)
        system._judged = [_frame_from_state(f) for f in state.get("judged_frames") or []]
        if system.backend is not None and state["map"] is not None:
            system.backend.load_state_dict(state["map"])
        return system


def _frame_state(frame: Frame) -> dict[str, Any]:
    """A kept frame for a snapshot (arrays as they are; intrinsics as a dict)."""
    return {"index": frame.index, "timestamp": frame.timestamp, "image": frame.image, "depth": frame.depth,
            "pose": frame.pose, "gt_pose": frame.gt_pose,
            "intrinsics": None if frame.intrinsics is None else frame.intrinsics.to_dict()}


def _frame_from_state(state: dict[str, Any]) -> Frame:
    def array(value: Any, dtype) -> np.ndarray | None:
        return None if value is None else np.asarray(value, dtype)

    return Frame(int(state["index"]), float(state["timestamp"]), np.asarray(state["image"], np.uint8),
                 intrinsics=None if state["intrinsics"] is None else Intrinsics.from_dict(state["intrinsics"]),
                 depth=array(state["depth"], np.float32), pose=array(state["pose"], np.float64),
                 gt_pose=array(state["gt_pose"], np.float64))


def _flat_snapshot(state: Any, arrays: Mapping[str, bytes] | None = None) -> dict[str, Any]:
    """A snapshot's state as one dict of format 1's keys (format 2 keeps the stages' parts packed apart; `arrays`:
    the large arrays an incremental snapshot keeps outside, by digest)."""
    if not isinstance(state, dict) or state.get("format") not in SNAPSHOT_FORMATS:
        raise ValueError("not a Flash-Mono SLAM snapshot")
    if state["format"] != SNAPSHOT_FORMAT:
        return state
    arrays = arrays or {}
    flat = {**unpack(state["tracking"], external=arrays), **unpack(state["loop"], external=arrays)}
    flat["map"] = None if state["map"] is None else unpack(state["map"], external=arrays)
    return flat


def _uncrop_intrinsics(intr: Intrinsics, geometry: tuple[float, tuple[int, int, int, int]], width: int,
                       height: int) -> Intrinsics:
    """Model-resolution intrinsics back at the input resolution (undo the centre crop, then the resize)."""
    scale, (left, top, _, _) = geometry
    return Intrinsics(intr.fx / scale, intr.fy / scale, (intr.cx + left) / scale, (intr.cy + top) / scale, width,
                      height)
