"""Settings of dense RGB-D odometry (`worker.tracking.rgbd_odometry.RgbdOdometry`). Thresholds are relative to
depth or image intensity, never in metres."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class RgbdOdometryConfig(BaseModel):
    """Dense RGB-D odometry settings."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    pyramid_levels: int = Field(3, ge=1, le=5, description="image pyramid levels (each half the previous size)")
    iterations: list[int] = Field([6, 8, 10], description="Gauss-Newton iterations per level, fine to coarse")
    max_points: int = Field(4000, ge=200, description="reference pixels per residual term and level")
    photometric_weight: float = Field(1.0, ge=0, description="weight of the photometric term (geometric: 1)")
    new_reference_overlap: float = Field(
        0.75, gt=0, le=1, description="a new reference keyframe once less than this fraction of it is still seen")
    new_reference_translation: float = Field(
        0.12, gt=0, description="... or once the camera moved this fraction of the reference's median depth")
    new_reference_rotation_deg: float = Field(10.0, gt=0, description="... or turned this much")
    min_overlap: float = Field(0.3, gt=0, le=1, description="tracking is lost below this overlap")
    max_photometric_residual: float = Field(
        0.12, gt=0, description="tracking is lost when the robust intensity residual (0..1 scale) exceeds this")
    blurred_photometric_residual: float = Field(
        0.3, gt=0, description="... up to this residual when the depth still fits (`max_geometric_residual`) and "
        "the view overlaps the reference well: a motion-blurred or re-exposed frame is tracked on its geometry")
    max_geometric_residual: float = Field(
        0.01, gt=0, description="... the robust depth residual, as a share of the reference's median depth, at most")
    max_jump: float = Field(
        0.5, gt=0, description="tracking is lost when the pose leaves the motion model's guess by more than this "
        "fraction of the median depth")
    reference_ring: int = Field(6, ge=1, le=64, description="past reference keyframes kept for relocalization")
    focal_guess: float = Field(
        0.8, gt=0.1, lt=5.0, description="frames without intrinsics: focal length as a share of the long side")
    seed_difference: float = Field(
        0.03, gt=0, description="a second alignment from the feature-based guess when it differs from the motion "
        "model's by more than this fraction of the median depth (or 2 degrees)")
    seed_residual_ratio: float = Field(
        1.5, gt=1, description="the feature-based guess is tried when an alignment's photometric residual exceeds "
        "this multiple of the recent ones (or it overlaps the reference poorly, or there is no motion history)")
    self_calibrate: bool = Field(True, description="frames without intrinsics: estimate the focal length from the "
                                 "first frames (else keep focal_guess)")
    calibration_motion: float = Field(
        0.06, gt=0, description="self-calibration runs once the camera moved this fraction of the first frame's "
        "median depth (or turned 10x this many degrees), over a third of calibration_frames at least")
    calibration_frames: int = Field(24, ge=3, le=120, description="... or after this many frames at the latest")
    reuse_keyframes: int = Field(
        64, ge=0, le=1024, description="keyframes kept (grey, float16 depth) as places to track against when the "
        "camera comes back; 0 = never reuse (the oldest beyond this are forgotten)")
    reuse_min_age: int = Field(
        30, ge=1, description="a keyframe is a place to come back to once this many frames old (younger ones are "
        "the camera's current stretch)")
    reuse_distance: float = Field(
        0.15, gt=0, description="a place is near when the camera is within this fraction of its median depth ...")
    reuse_rotation_deg: float = Field(15.0, gt=0, description="... and turned less than this from it")
    reuse_overlap: float = Field(
        0.7, gt=0, le=1, description="a frame seeing at least this fraction of the place it tracks against is "
        "covered: it asks for no new keyframe")
