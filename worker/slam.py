"""The SLAM system: one object per session, frame in -> pose out, with a 2DGS map behind it.

Three stages, each with its own module and input queue (the Tracking / LocalMapping / LoopClosing split of
ORB-SLAM3): the tracking stage (worker.pipeline.tracking_stage, in the caller's thread) tracks each frame, publishes
its pose at once and hands keyframes on; the mapping stage (worker.pipeline.mapping_stage, its own thread) maps
keyframes, shedding work when it falls behind; the loop-closing stage (worker.pipeline.loop_stage, its own thread)
keeps the pose graph, detects and verifies loops and hands optimised keyframe poses back, which tracking applies as
a new trajectory revision. Tracking never waits for either. `SlamConfig.threaded=False` runs every stage inline in
the caller: deterministic.

The first frame decides the parts (worker.pipeline.assembly): the pose source (worker.tracking, `choose_tracking`:
device poses, RGB-D odometry, visual odometry or photo registration, the learned model) and the keyframe surfels'
source (worker.pipeline.depth_sources). This module assembles them and serves the session's API (snapshots:
worker.pipeline.snapshot)."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from protocol.limits import MAX_RENDER_SIDE
from worker.config import SlamConfig
from worker.data.frame import Frame, FrameResult
from worker.events import EngineEvent
from worker.geometry import Intrinsics
from worker.maps.session_in_map import SessionInMap
from worker.pipeline import snapshot
from worker.pipeline.assembly import Assembly, assemble, idle_loop_stage, mapping_stage
from worker.pipeline.depth_registration import DepthRegistration
from worker.pipeline.finish import finish_session
from worker.pipeline.finish_status import FinishStatus
from worker.pipeline.judged_start import JudgedStart
from worker.pipeline.keyframes import MotionKeyframeSelector
from worker.pipeline.learned_model import custom_model
from worker.pipeline.session_camera import SessionCamera
from worker.pipeline.session_stats import live_stats, pose_source_choice, session_stats
from worker.pipeline.snapshot_future import SnapshotFuture
from worker.pipeline.stage_times import StageTimes
from worker.pipeline.tracking_stage import TrackingStage
from worker.tracking.sources import choose_tracking


class SlamSystem:
    """Monocular / posed / RGB-D 2DGS SLAM over a stream of `Frame`s (see the module docstring)."""

    def __init__(self, config: SlamConfig | None = None, intrinsics: Intrinsics | None = None,
                 in_map: SessionInMap | None = None) -> None:
        self.config = config if config is not None else SlamConfig.preset("default")
        if not isinstance(self.config, SlamConfig):
            raise ValueError(f"config must be a SlamConfig, got {type(self.config).__name__}")
        torch.set_num_threads(self.config.num_threads)
        self.intrinsics, self.in_map = intrinsics, in_map  # in_map: the stored map it runs in (worker.maps)
        self.timings = StageTimes()  # the runtime breakdown of paper appendix E
        self.counters: dict[str, float] = {"frames": 0, "frames_tracked": 0, "frames_registered_later": 0,
                                           "keyframes": 0, "loops": 0, "frontend_seconds": 0.0,
                                           "wall_seconds": 0.0}
        self.camera = SessionCamera(intrinsics, lambda width, height: self.tracking_stage.source_intrinsics(
            width, height))
        self.tracking_stage = TrackingStage(MotionKeyframeSelector.from_config(self.config.frontend), self.camera,
                                            self.counters, self.timings, max_side=self.config.tracking.max_side)
        self.tracking_stage.loop_closing = idle_loop_stage(self.config, self.timings)
        self.mapping_stage = mapping_stage(self.config, self.timings)  # a thread, or a process of its own
        self.judged_start = JudgedStart(self.tracking_stage)
        # Decided by the first frame (worker.pipeline.assembly): None before it
        self.parts: Assembly | None = None
        self.tracking = self.mode = self.depth_source = self.model_id = None
        self.learned = self.model = self.loop_closer = self.depth_points = None
        self.with_depth = False
        self.finished = False
        self.started: float | None = None
        self.wall_offset = 0.0  # wall time of the run before a restore
        self.finish_events: list[EngineEvent] = []  # events of finish() (no frame result carries them)
        self.finish_status = FinishStatus()  # finish()'s phase and progress, for progress bars and messages
        self.depth_registration = DepthRegistration(self.config.input.depth_camera,
                                                    self.config.input.detect_misregistration_frames)

    # ------------------------------------------------------------------------------------------- the parts
    def setup(self, tracking: str, with_depth: bool) -> None:
        """Assemble the session's parts for pose source `tracking` (the first frame, or a restore)."""
        self.with_depth = with_depth
        self.tracking_stage.loop_closing.close()
        self.parts = parts = assemble(self.config, tracking, with_depth, self.tracking_stage, self.mapping_stage,
                                      self.timings, self.in_map)
        self.tracking, self.mode, self.depth_source = parts.tracking, parts.mode, parts.depth_source
        self.learned, self.model, self.model_id = parts.learned, parts.model, parts.model_id
        self.loop_closer, self.depth_points = parts.loop_closer, parts.depth_points

    @property
    def loop_stage(self):
        """The loop-closing stage (worker.pipeline.loop_stage)."""
        return self.tracking_stage.loop_closing

    @property
    def pose_graph(self):
        """The keyframe pose graph (the loop-closing stage's: read it only while that stage is idle)."""
        return self.loop_stage.pose_graph

    pose_source = property(lambda self: self.tracking_stage.pose_source)
    tracker = property(lambda self: None if self.learned is None else self.learned.tracker)

    @property
    def model_intrinsics(self) -> Intrinsics | None:
        """The camera at model resolution (given or estimated), when the model runs."""
        return None if self.learned is None else self.learned.intrinsics

    @property
    def revision(self) -> int:
        """The trajectory revision: grows each time a loop closure rewrites past poses."""
        return self.tracking_stage.revision

    @property
    def needs_every_frame(self) -> bool:
        """Whether frames go through the judged start now (device poses are being judged)."""
        return self.judged_start.judging

    @property
    def keeps_every_frame(self) -> bool:
        """Whether a live stream should skip no frame now: device poses judged, or photos (each one registered)."""
        return self.needs_every_frame or bool(getattr(getattr(self, "pose_source", None), "keeps_every_frame", False))

    @property
    def last_frame_mapped(self) -> int | None:
        """The final frame's index when finish() mapped it too."""
        return self.tracking_stage.last_frame_mapped

    @property
    def num_gaussians(self) -> int:
        return 0 if self.mapping_stage is None else self.mapping_stage.num_gaussians()

    def estimated_intrinsics(self) -> Intrinsics | None:
        """The camera at the input frames' resolution: given, else estimated (see SessionCamera.estimated)."""
        return self.camera.estimated()

    # ------------------------------------------------------------------------------------------- frames
    def push(self, frame: Frame) -> FrameResult:
        """Track one frame (and queue its keyframe for mapping); returns its pose and events."""
        if self.finished:
            raise ValueError("this SLAM session is finished; start a new one")
        if not isinstance(frame, Frame):
            raise ValueError(f"push() takes a worker.data.Frame, got {type(frame).__name__}")
        self._raise_if_a_stage_failed()
        start = time.perf_counter()
        self.started = self.started or start
        frame, registration_events = self.depth_registration.apply(frame, self.camera.of_frame(frame))
        self._check_frame(frame)
        result = self.judged_start.push(frame) if self.needs_every_frame else self.tracking_stage.process(frame)
        result.events += registration_events
        self.counters["frames"] += 1
        self.counters["frontend_seconds"] += time.perf_counter() - start
        self.counters["wall_seconds"] = self.wall_offset + time.perf_counter() - self.started
        return result

    def _check_frame(self, frame: Frame) -> None:
        size = (frame.width, frame.height)
        if self.camera.frame_size is None:
            posed = frame.pose is not None and self.config.input.pose_mode != "ignore"
            with_depth = frame.depth is not None and self.config.input.use_depth
            self.camera.frame_size = size
            self.setup(choose_tracking(self.config.tracking.source, frame, posed, with_depth,
                                       custom_model(self.config)), with_depth)
        elif size != self.camera.frame_size:
            raise ValueError(f"frame {frame.index} is {size[0]}x{size[1]}, the session's frames are "
                             f"{self.camera.frame_size[0]}x{self.camera.frame_size[1]}")
        if self.tracking == "rgbd_odometry" and frame.depth is None:
            raise ValueError(f"frame {frame.index} has no depth, but this session tracks by RGB-D odometry")

    def finish(self) -> None:
        """Drain the stages (every keyframe mapped, every loop query answered, the corrections applied), run the
        final refinement, stop the stages' threads (worker.pipeline.finish)."""
        if self.finished:
            return
        finish_session(self)
        self.close()
        if self.started is not None:
            self.counters["wall_seconds"] = self.wall_offset + time.perf_counter() - self.started
        self.finished = True

    def close(self) -> None:
        """Stop the stages' threads without further work (idempotent)."""
        if self.mapping_stage is not None:
            self.mapping_stage.close()
        self.loop_stage.close()

    def _raise_if_a_stage_failed(self) -> None:
        if self.mapping_stage is not None:
            self.mapping_stage.raise_if_failed()
        self.loop_stage.raise_if_failed()

    # ------------------------------------------------------------------------------------------- reads
    def trajectory(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]:
        """[(index, timestamp, c2w pose 4x4)] of "all" frames or the "keyframes", at the current revision."""
        return self.tracking_stage.trajectory.listing(which)

    def render_view(self, pose_c2w: np.ndarray, K: np.ndarray | torch.Tensor, width: int, height: int,
                    as_captured_at: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render the map: (rgb uint8 [h,w,3], depth float32 [h,w]) seen from c2w `pose_c2w` with intrinsics K, in
        the map's exposure-normalised colours or, with `as_captured_at` (a frame index), under the exposure the
        camera had at that frame (interpolated between its keyframes: what the photo of that frame shows)."""
        if self.mapping_stage is None:
            raise ValueError("mapping is disabled in this session's config")
        pose = np.asarray(pose_c2w, np.float64)
        Km = torch.as_tensor(np.asarray(K, np.float64), dtype=torch.float32)
        if pose.shape != (4, 4) or tuple(Km.shape) != (3, 3):
            raise ValueError("render_view needs a 4x4 pose and a 3x3 K")
        if not (0 < width <= MAX_RENDER_SIDE and 0 < height <= MAX_RENDER_SIDE):
            raise ValueError(f"render size must be within 1..{MAX_RENDER_SIDE}, got {width}x{height}")
        renderer = self.mapping_stage if self.in_map is None else self.in_map.renderer(self.mapping_stage)
        out = renderer.render(pose, Km, int(width), int(height), as_captured_at)
        rgb = (out.rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return rgb, out.depth.to(torch.float32).cpu().numpy()

    def export_ply(self) -> bytes:
        """The map as a binary PLY (3DGS/2DGS layout)."""
        if self.mapping_stage is None:
            raise ValueError("mapping is disabled in this session's config")
        return self.mapping_stage.to_ply_bytes()

    def stats(self) -> dict[str, Any]:
        """Counters for status pages and metrics (worker.pipeline.session_stats)."""
        return session_stats(self)

    def live_stats(self) -> dict[str, Any]:
        """What a live client watches, cheap to read while frames stream (see session_stats.live_stats)."""
        return live_stats(self)

    def pose_source_choice(self) -> dict[str, Any]:
        """How the session uses the frames' device poses (see session_stats.pose_source_choice)."""
        return pose_source_choice(self)

    # ------------------------------------------------------------------------------------------- snapshots
    def snapshot(self) -> bytes:
        """Everything needed to continue this session, as msgpack bytes (waits for the stages' parts)."""
        return self.begin_snapshot().result()

    def begin_snapshot(self, stored_chunks: Mapping[int, int] | None = None) -> SnapshotFuture:
        """A snapshot of the session as of now, without waiting (worker.pipeline.snapshot); `result()` gives the bytes
        that `restore` takes. With `stored_chunks` (chunk -> version already stored) it is incremental: sealed
        trajectory chunks and large arrays stay out of the bytes, in `future.chunks` (a ChunkWrite)."""
        return snapshot.begin_snapshot(self, stored_chunks)

    @classmethod
    def restore(cls, data: bytes, chunks: Mapping[int | str, bytes] | None = None,
                in_map: SessionInMap | None = None) -> SlamSystem:
        """A system continuing from `snapshot()` bytes (never unpickles), in the stored map `in_map` if any;
        `chunks`: what an incremental snapshot left out (trajectory chunks by number, arrays by digest)."""
        return snapshot.restore(cls, data, chunks, in_map)
