"""The pose source of a session, built from its name (see worker.tracking.sources.choose_tracking)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from worker.config import SlamConfig
from worker.tracking.sources import DevicePoses, ModelTracking


def build_pose_source(tracking: str, config: SlamConfig, with_depth: bool, submit_prior: Callable[[Any], None],
                      model: ModelTracking | None = None):
    """The pose source `tracking` ("device", "model", "rgbd_odometry" or "visual_odometry": RGB only, video or
    photos) with the session's settings. Device poses follow `input.pose_mode`: "seeded" (and "auto" with depth)
    tracks from the device's motion and sends the device poses as keyframe priors through `submit_prior`; "auto"
    without depth judges them over the first frames (worker.tracking.pose_choice); else they are the poses.
    `model`: the learned model as a pose source, for "model". Device poses are re-timed by the device clock first
    (`input.device_clock`: the source's `device_clock`, worker.tracking.device_clock) unless it is off with no
    offset given."""
    source = _device_or_other(tracking, config, with_depth, submit_prior, model)
    clock = config.input.device_clock
    if tracking == "device" and (clock.mode == "estimate" or clock.offset_s != 0.0):
        from worker.tracking.device_clock import DeviceClock

        source.device_clock = DeviceClock(clock, use_depth=with_depth, background=config.threaded)
    return source


def _device_or_other(tracking: str, config: SlamConfig, with_depth: bool, submit_prior: Callable[[Any], None],
                     model: ModelTracking | None):
    pose_mode = config.input.pose_mode
    if tracking == "device" and (pose_mode == "seeded" or (pose_mode == "auto" and with_depth)):
        from worker.tracking.seeded import seeded_tracking

        return seeded_tracking(config, with_depth, submit_prior)
    if tracking == "device" and pose_mode == "auto":
        from worker.tracking.pose_choice import ChosenDevicePoses
        from worker.tracking.seeded import seeded_tracking

        return ChosenDevicePoses(lambda: seeded_tracking(config, False, submit_prior), config.input.pose_choice)
    if tracking == "device":
        return DevicePoses()
    if tracking == "model":
        if model is None:
            raise ValueError("tracking 'model' needs the learned model")
        return model
    if tracking == "rgbd_odometry":
        from worker.tracking.rgbd_odometry import RgbdOdometry

        return RgbdOdometry(config.tracking.rgbd)
    if tracking == "visual_odometry":
        return _monocular(config)
    raise ValueError(f"unknown pose source {tracking!r}")


def _monocular(config: SlamConfig):
    """RGB only: visual odometry, photo registration, or (source auto) the one the first frames' timing
    chooses (worker.tracking.monocular_choice)."""
    from worker.tracking.photos import PhotoRegistration
    from worker.tracking.visual_odometry import VisualOdometry

    tracking = config.tracking
    if tracking.source == "photos":
        return PhotoRegistration(tracking.photos)
    if tracking.source == "visual_odometry" or tracking.photos.min_interval_s == 0:
        return VisualOdometry(tracking.visual)
    from worker.tracking.monocular_choice import MonocularChoice

    return MonocularChoice(lambda: VisualOdometry(tracking.visual), lambda: PhotoRegistration(tracking.photos),
                           tracking.photos.min_interval_s)
