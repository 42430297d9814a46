"""A session's figures for status pages, metrics and live clients, read from its stages."""

from __future__ import annotations

from typing import Any

from worker.pipeline.depth_sources import ModelSurfels
from worker.pipeline.session_parts import SessionParts

LIVE_MAPPING_KEYS = ("mapping_lag_keyframes", "mapping_lag_s", "keyframes_shed", "keyframes_owed",
                     "keyframes_caught_up")


def session_stats(system: SessionParts) -> dict[str, Any]:
    """Counters, rates, the stages' backlogs and the runtime breakdown."""
    frames, wall = system.counters["frames"], system.counters["wall_seconds"]
    mapping = system.mapping_stage
    source = system.tracking_stage.depth_source
    path = ({"path_given": source.path_given, "path_tracked": source.path_tracked}
            if isinstance(source, ModelSurfels) else {"path_given": 0.0, "path_tracked": 0.0})
    return {**system.counters, **path, "revision": system.revision, "mode": system.mode,
            "num_gaussians": system.num_gaussians, "fps": frames / wall if wall > 0 else 0.0,
            "backend_pending": 0 if mapping is None else mapping.pending,
            "backend_seconds": 0.0 if mapping is None else mapping.busy_seconds,
            "keyframes_mapped": 0 if mapping is None else mapping.keyframes_mapped,
            "mapping_process_restarts": 0 if mapping is None else mapping.restarts,
            **live_stats(system), "pose_source": pose_source_choice(system)["pose_source"],
            "pose_strategy": pose_strategy(system),
            "device_clock": device_clock(system), "final_adjustment": final_adjustment(system),
            "runtime_breakdown": system.timings.breakdown(int(frames))}


def live_stats(system: SessionParts) -> dict[str, Any]:
    """What a live client watches, cheap to read while frames stream: how far mapping lags (keyframes waiting,
    seconds the oldest has waited), what it shed, what it still owes and caught up since (refinement made up while
    idle), and the loop-closing stage's backlog."""
    mapping = ({"mapping_lag_keyframes": 0, "mapping_lag_s": 0.0, "keyframes_shed": {}, "keyframes_owed": 0,
                "keyframes_caught_up": 0} if system.mapping_stage is None else system.mapping_stage.stats())
    return {**{key: mapping[key] for key in LIVE_MAPPING_KEYS}, "loop_pending": system.loop_stage.pending}


def pose_strategy(system: SessionParts) -> str | None:
    """What tracks the frames: the pose source's name (RGB only: `visual_odometry` for video, `photos` for photo
    registration, once the first frames chose); None before the first frame."""
    source = getattr(system, "pose_source", None)
    return None if source is None else source.name


def pose_source_choice(system: SessionParts) -> dict[str, Any]:
    """How the session uses the frames' device poses: `pose_source` (prior, fixed or seeded; None when it does not
    use them) and, for `pose_mode` auto without depth, whether it was judged yet and the agreement figures it was
    chosen by (`worker.tracking.pose_choice`)."""
    if system.tracking != "device":
        return {"pose_source": None, "pose_agreement": None}
    summary = getattr(system.pose_source, "summary", None)
    if summary is not None:
        return summary()
    pose_mode = system.config.input.pose_mode
    return {"pose_source": "seeded" if pose_mode == "auto" else pose_mode, "pose_agreement": None}


def device_clock(system: SessionParts) -> dict[str, Any] | None:
    """The device pose clock's offset applied and how it was measured (`worker.tracking.device_clock`); None when
    the session's frames carry no device poses or the clock is off."""
    clock = getattr(system.pose_source, "device_clock", None) if system.tracking == "device" else None
    return None if clock is None else clock.summary()


def final_adjustment(system: SessionParts) -> dict[str, Any] | None:
    """Visual odometry's final bundle adjustment (`worker.tracking.global_adjustment`), once the session finished:
    whether it moved the keyframes, the revisit pairs verified, the points joined, the observations and the seconds
    it took; None before the finish and for other pose sources."""
    result = getattr(getattr(system, "pose_source", None), "final_adjustment", None)
    if result is None:
        return None
    return {"applied": bool(result.poses), "keyframes": len(result.poses), "pairs": result.pairs,
            "points_joined": result.joined, "observations": result.observations, "seconds": round(result.seconds, 3),
            "local_scales": None if result.local_scales is None else [round(v, 4) for v in result.local_scales]}
