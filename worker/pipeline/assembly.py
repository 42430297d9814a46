"""A session's parts, assembled at its first frame once what the frames carry is known.

From the pose source's name and whether the frames carry depth: where keyframe surfels come from (a depth source,
worker.pipeline.depth_sources), the learned model where anything needs it, the pose source (worker.tracking.factory),
the loop closer and the keyframe points it verifies with, and a loop-closing stage with a pose graph whose scale is
fixed when poses and depth are metric. The parts are wired to each other here and nowhere else.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

from worker.config import LoopConfig, SlamConfig
from worker.loop.keyframe_alignment import KeyframeAlignment
from worker.loop.pose_graph import DEFAULT_SIGMAS, EdgeSigmas, Sim3PoseGraph
from worker.maps.session_in_map import SessionInMap
from worker.pipeline.depth_sources import (
    DepthSource,
    ModelSurfels,
    MultiViewDepth,
    SensorDepth,
    choose_depth_source,
    stereo_builder,
)
from worker.pipeline.learned_model import LearnedModel, load_model
from worker.pipeline.loop_closer import DepthKeyframePoints, LoopCloser
from worker.pipeline.loop_stage import LoopClosingStage
from worker.pipeline.mapping_process import MappingProcess
from worker.pipeline.mapping_stage import MappingStage
from worker.pipeline.stage_times import StageTimes
from worker.pipeline.tracking_stage import TrackingStage
from worker.tracking.factory import build_pose_source

log = logging.getLogger(__name__)

# Log-scale standard deviation of pose-graph edges when poses and depth are metric: the scale is known.
METRIC_LOG_SCALE_SIGMA = 1e-4
# The engine's mode (metrics, stats) for each pose source.
MODE_OF_TRACKING = {"device": "posed", "model": "monocular", "rgbd_odometry": "rgbd_odometry",
                    "visual_odometry": "visual_odometry"}
TRACKING_OF_MODE = {mode: tracking for tracking, mode in MODE_OF_TRACKING.items()}


@dataclass
class Assembly:
    """What a session's first frame decided and built."""

    tracking: str
    depth_source: str  # "sensor", "mvs" or "model"
    learned: LearnedModel | None
    model: Any  # the network (of the learned model, or the multi-view filler's), or None
    model_id: str | None
    loop_closer: LoopCloser | None
    depth_points: DepthKeyframePoints | None
    loop_stage: LoopClosingStage

    @property
    def mode(self) -> str:
        return MODE_OF_TRACKING[self.tracking]


def assemble(config: SlamConfig, tracking: str, with_depth: bool, stage: TrackingStage,
             mapping: MappingStage | MappingProcess | None, timings: StageTimes,
             in_map: SessionInMap | None = None) -> Assembly:
    """Build the session's parts for pose source `tracking` and wire them into `stage` and `mapping`; a session
    in a stored map (`in_map`) has tracking query it and loop closing find the queries in it."""
    source_name = choose_depth_source(config.input.depth_source, tracking, with_depth)
    needs_model = tracking == "model" or source_name == "model" or (with_depth and config.input.surfel_init == "model")
    learned = LearnedModel.build(config) if needs_model else None
    model, model_id = (learned.model, learned.model_id) if learned is not None else (None, None)
    depth_source: DepthSource | None = None
    if mapping is not None:
        if source_name == "mvs":
            if config.input.mvs_fill == "model" and model is None:
                model, model_id = load_model(config)
            depth_source = _multiview(config, stage, mapping, model)
        else:
            depth_source = _single_view(config, tracking, with_depth, stage, learned, timings)
    closer, depth_points = _loop_closer(config, tracking, with_depth, isinstance(depth_source, MultiViewDepth),
                                        learned, model, timings)
    loop_stage = _loop_stage(config, tracking, with_depth, closer, depth_points, timings)
    stage.loop_closing = loop_stage
    stage.depth_source = depth_source
    stage.mapping = mapping
    stage.with_depth = with_depth
    stage.pose_source = build_pose_source(tracking, config, with_depth, stage.loop_closing_submit,
                                          None if learned is None else learned.tracking)
    stage.timing_stage = "frontend_inference" if tracking == "model" else "frontend_tracking"
    stage.events.reprojects_points = depth_points is not None
    stage.loop_queries = None if closer is None else (
        "after_depth" if isinstance(depth_source, MultiViewDepth) else "sensor" if depth_points is not None
        else "model")
    if learned is not None:
        stage.model_intrinsics = lambda: learned.intrinsics
        stage.camera.model_estimate = learned.intrinsics_at
    if mapping is not None:
        mapping.loop_closing = stage.loop_closing_submit
    if in_map is not None:
        in_map.attach(session_metric=with_depth or tracking == "device", device_poses=tracking == "device")
        stage.in_map = loop_stage.in_map = in_map
        in_map.start_loading()
    log.info("session tracking: %s (mode %s), surfels from %s", tracking, MODE_OF_TRACKING[tracking], source_name)
    return Assembly(tracking, source_name, learned, model, model_id, closer, depth_points, loop_stage)


def mapping_stage(config: SlamConfig, timings: StageTimes) -> MappingStage | MappingProcess | None:
    """The session's mapping stage: in a process of its own where `mapping.process` asks for it (and the session
    is threaded, and no model fills its depth), else a thread; None with mapping disabled."""
    if not config.mapping.enabled:
        return None
    if config.mapping.process and config.threaded and config.input.mvs_fill != "model":
        return MappingProcess(config, timings)
    return MappingStage(config.mapping, config.threaded, config.queue_size, config.device, timings)


def _multiview(config: SlamConfig, stage: TrackingStage, mapping: MappingStage | MappingProcess,
               model: Any) -> MultiViewDepth:
    """Multi-view stereo: the frame ring in tracking, the builder in mapping."""
    builder = stereo_builder(config, model)
    mapping.use_multiview_depth(builder)
    return MultiViewDepth(stage.camera, config.input.mvs_buffer_frames, config.input.mvs_frames_after, builder)


def _single_view(config: SlamConfig, tracking: str, with_depth: bool, stage: TrackingStage,
                 learned: LearnedModel | None, timings: StageTimes) -> DepthSource | None:
    """The frame's own depth, or the model's prediction (with the depth for the means where asked, or where the
    poses are not in the depth's units)."""
    metric_poses = tracking in ("device", "rgbd_odometry")
    if with_depth and (learned is None or (config.input.surfel_init == "depth" and metric_poses)):
        return SensorDepth(stage.camera)
    if learned is None:
        return None
    return ModelSurfels(learned.tracking, config.frontend, use_depth=with_depth, metric_poses=metric_poses,
                        own_poses=tracking == "model", timings=timings)


def _loop_closer(config: SlamConfig, tracking: str, with_depth: bool, multiview: bool, learned: LearnedModel | None,
                 model: Any, timings: StageTimes) -> tuple[LoopCloser | None, DepthKeyframePoints | None]:
    """The loop closer and the keyframe points it verifies with, when this session closes loops."""
    if not config.loop.enabled or (tracking == "device" and config.input.pose_mode == "fixed"):
        return None, None
    if tracking == "model":
        return LoopCloser(config.loop, model=model, tracker=learned.tracker, bag=learned.bag, timings=timings), None
    if not with_depth and not multiview:
        log.warning("%s without depth: loop closure is off (no points to relocalize with)", tracking)
        return None, None
    points = DepthKeyframePoints()
    return LoopCloser(config.loop, model=model, depth_points=points, timings=timings), points


def _loop_stage(config: SlamConfig, tracking: str | None, with_depth: bool, closer: LoopCloser | None,
                depth_points: DepthKeyframePoints | None, timings: StageTimes) -> LoopClosingStage:
    """The loop-closing stage; inline with the learned model, whose tracker state loop closure reads."""
    metric = tracking in ("device", "rgbd_odometry") and with_depth
    device_poses = config.input.device_poses
    solve_priors_every = (device_poses.graph_solve_keyframes if device_poses.drift_correction == "pose_graph"
                          and tracking == "device" and not with_depth else 0)
    graph = pose_graph(config, metric, monocular=tracking == "visual_odometry")
    return LoopClosingStage(config.loop, graph, closer, depth_points, metric=metric,
                            threaded=config.threaded and tracking != "model", timings=timings,
                            solve_priors_every=solve_priors_every,
                            alignment=_keyframe_alignment(config.loop) if metric and closer is not None else None)


def _keyframe_alignment(lc: LoopConfig) -> KeyframeAlignment | None:
    """Dense edges between neighbouring keyframes with sensor depth and metric poses (RGB-D, posed RGB-D), unless
    configured off."""
    if not lc.enabled or lc.covisible_neighbours == 0:
        return None
    return KeyframeAlignment(lc.covisible_neighbours, lc.covisible_distance, lc.covisible_rotation_deg,
                             lc.covisible_min_overlap, lc.covisible_max_residual, lc.covisible_max_photometric)


def idle_loop_stage(config: SlamConfig, timings: StageTimes) -> LoopClosingStage:
    """The loop-closing stage of a session before its first frame (replaced by `assemble`)."""
    return _loop_stage(config, None, False, None, None, timings)


def pose_graph(config: SlamConfig, metric: bool = False, monocular: bool = False) -> Sim3PoseGraph:
    """The keyframe pose graph; `metric` (given poses and depth) leaves the scale no freedom; `monocular` (visual
    odometry) takes `loop.monocular_*` for the odometry's scale, its loops' sigmas and their kernel."""
    lc = config.loop
    sigmas = {kind: EdgeSigmas(s.rotation, s.translation, METRIC_LOG_SCALE_SIGMA if metric else s.log_scale)
              for kind, s in {**DEFAULT_SIGMAS, "loop": EdgeSigmas(0.02, 0.02, 0.02)}.items()}
    robust_k = lc.robust_k
    if monocular and not metric:
        for kind in ("sequential", "inter_submap"):
            sigmas[kind] = replace(sigmas[kind], log_scale=lc.monocular_scale_sigma)
        sigmas["loop"] = EdgeSigmas(sigmas["loop"].rotation, lc.monocular_loop_translation_sigma,
                                    lc.monocular_loop_scale_sigma)
        robust_k = lc.monocular_robust_k
    return Sim3PoseGraph(robust=None if lc.robust_kernel == "none" else lc.robust_kernel, robust_k=robust_k,
                         sigmas=sigmas)
