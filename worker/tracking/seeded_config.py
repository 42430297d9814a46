"""Settings of seeded tracking (`worker.tracking.seeded.SeededTracking`): how far device poses are trusted."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class DevicePoseConfig(BaseModel):
    """The stated uncertainty of a device's poses and the thresholds that call a device motion a jump."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    prior_translation: float = Field(
        0.10, gt=0, le=100, description="standard deviation (pose units, metres for ARKit/ARCore) of a device pose "
        "as an absolute prior on its keyframe in the pose graph")
    prior_rotation_deg: float = Field(2.0, gt=0, le=180, description="... and of its orientation, in degrees")
    prior_inflation: float = Field(
        10.0, ge=0, description="a keyframe prior's standard deviations are at least this times the device pose's "
        "distance and angle from the tracked pose (0: the stated ones only)")
    seed_translation: float = Field(
        0.01, gt=0, description="the device's motion into a frame replaces the odometry's constant-velocity guess "
        "when the two differ by more than this (pose units) ...")
    seed_rotation_deg: float = Field(1.0, gt=0, le=180, description="... or by more than this rotation")
    jump_translation: float = Field(
        0.05, gt=0, description="a frame's device motion that differs from the tracked motion by more than this "
        "(pose units) is a jump (relocalisation, glitch): it is not used and the next keyframe gets no prior")
    jump_rotation_deg: float = Field(3.0, gt=0, le=180, description="... or by more than this rotation")
    jump_relative: float = Field(
        0.25, ge=0, le=10, description="... both thresholds grow by this fraction of the tracked motion's own "
        "distance and angle: frames far apart (sparse keyframes, a dropped stretch of the stream) carry an odometry "
        "error in proportion to their motion, which is not a jump (0: absolute thresholds only)")
    arbitrate_jumps: bool = Field(
        True, description="with depth: before a disagreement is called a device jump, the frame is aligned again "
        "from the device's motion; where that alignment fits the images clearly better (`slip_fit_ratio`), the "
        "odometry slipped, not the device: its pose is replaced (`odometry_slip` event) and the device kept")
    slip_fit_ratio: float = Field(
        0.9, gt=0, le=1, description="... clearly better: one robust residual (intensity or depth) at most this times "
        "the odometry's, the other at most 1/this times it, and the overlap with the reference not smaller by more "
        "than 0.05")
    scale_keyframes: int = Field(
        8, ge=0, le=256, description="monocular: the odometry's scale is measured again at each keyframe, as the "
        "device's over the odometry's distances between the last this many keyframes (no jump between them), and "
        "the world re-anchored there so that no pose jumps; 0: only from the initialisation's baseline")
    drift_correction: Literal["reanchor", "settle", "pose_graph"] = Field(
        "reanchor", description="monocular: how the device's scale meets the odometry's drifting one. reanchor (the "
        "default): measured again at every keyframe and the world re-anchored there, so the trajectory keeps the "
        "device's scale while new keyframes and the map built before them differ in scale (offline, 320x240 TUM "
        "fr1/xyz with its motion capture: 2.53 cm, 19.13 dB, below RGB only's 1.98 cm, 20.73 dB; KITTI 00 0-199 at "
        "620x188: 30 cm, 20.95 dB; live on TUM, five runs: 2.1-4.6 cm, 16.6-18.9 dB). settle: the "
        "initialisation's two-view scale is measured again at each keyframe until a full `scale_keyframes` window "
        "measured it, then kept: the map stays at one scale, the device still seeds the odometry and checks it for "
        "jumps (a jump measures the scale again), and its poses are priors a loop closure weighs; between loops the "
        "trajectory drifts from the device's as the odometry does (offline TUM 1.80 cm, 21.69 dB; KITTI 21.21 dB "
        "but 1.74 m; live on TUM, five runs: 2.8-5.0 cm, 15.9-20.1 dB: not the default). pose_graph: settled, then "
        "the pose graph is solved with the device priors every `graph_solve_keyframes` keyframes, moving past "
        "keyframes and their part of the map (Sim(3): scale included) toward the device's trajectory (a "
        "`drift_corrected` revision; offline TUM 1.53 cm, 22.31 dB; KITTI 3.5 cm, but 19.55 dB: the keyframes' "
        "parts of the map move apart where no loop ties them)")
    settle_tolerance: float = Field(
        0.0, ge=0, le=1, description="settle: where the scale measured over the last `scale_keyframes` keyframes "
        "differs from the kept one by more than this share, the world is re-anchored once at the measured scale and "
        "kept at it again (0: never). For drives that never come back: KITTI with 0.1, ATE 37 cm and 21.13 dB; on "
        "TUM fr1/xyz, which loops all the time, 3.47 cm and 18.33 dB")
    graph_solve_keyframes: int = Field(
        4, ge=1, le=1000, description="... pose_graph: solved after this many keyframe priors")
    scale_min_baseline: float = Field(
        0.02, gt=0, description="... keyframe distances shorter than this (pose units) are not measured")
    resume_when_lost: bool = Field(
        True, description="with depth: a frame the RGB-D odometry loses is aligned again from the device's pose, "
        "and where that fails too the odometry restarts there (`relocalized`, method device_pose), so that "
        "tracking and keyframes go on while the device moves (off: the device's motion is followed, without "
        "keyframes, until the odometry relocalises by itself)")
    resume_sharpness: float = Field(
        0.0, ge=0, le=1, description="... but no restart on a frame less sharp (variance of the Laplacian) than this "
        "times the odometry's reference: through motion blur the device's motion is followed until a sharp frame "
        "(0: off, the default: the Laplacian's variance follows the scene's texture as much as the blur; on the "
        "fr3/cabinet keyframes a ratio of 0.6 blocked 17 frames of restarts where the view turned to the bare floor)")
    resume_after_s: float = Field(
        0.3, ge=0, description="... and no restart before the odometry has been lost this long (seconds of frame "
        "time): a short loss is left to relocalise against the odometry's references, from the device's pose")


class PoseChoiceConfig(BaseModel):
    """pose_mode auto without depth: how the device poses are judged against the images over the first frames
    (`worker.tracking.pose_choice`)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    max_ratio: float = Field(
        1.5, gt=0, description="the device poses are the odometry (prior) while their three-view reprojection error "
        "is at most this times the error of poses fitted to the same tracks from the images alone (a ratio, free of "
        "scale and resolution: about 0.4-0.7 for exact poses, 1 where the device is as good as three frames' own "
        "fit); above it, visual odometry tracks from the device's motion and the device poses are priors (seeded)")
    triples: int = Field(8, ge=1, le=100, description="frame triples with parallax the verdict waits for ...")
    within_frames: int = Field(
        30, ge=0, le=1000, description="... or at most this many frames, judged on the triples measured by then; 0: no "
        "judging, always prior. While judging, frames get the device's poses and no keyframe; at the verdict they go "
        "through the chosen source from the first")
    min_triples: int = Field(
        3, ge=1, le=100, description="with fewer triples than this by then (a slow start, sparse views), the device "
        "poses are kept (prior): one or two triples' median is no evidence against them")
    step: int = Field(2, ge=1, le=30, description="frames between the views of a triple")


class DeviceClockConfig(BaseModel):
    """Frames with device poses: the offset between the device's pose clock and the camera's
    (`worker.tracking.device_clock`). A frame's device pose is taken as the camera's pose at `timestamp + offset`;
    the device trajectory is read at `timestamp - offset` instead."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    mode: Literal["estimate", "off"] = Field(
        "estimate", description="estimate: measured from the images' own frame-to-frame motion over the first frames "
        "with motion (a few ms a frame while measuring, nothing after), trusted only with a clear minimum "
        "(`max_uncertainty_s`), else `offset_s` is kept; off: `offset_s` only")
    offset_s: float = Field(
        0.0, ge=-0.5, le=0.5, description="the device clock minus the camera's, seconds (a frame's device pose is "
        "the pose at its timestamp plus this), as the client knows it: used from the first frame, and kept where "
        "the estimate is not trusted")
    window_frames: int = Field(
        90, ge=10, le=1000, description="estimate: measured once this many frames with device poses came ...")
    retry_frames: int = Field(30, ge=1, le=1000, description="... again every this many more while not trusted ...")
    max_frames: int = Field(
        300, ge=10, le=5000, description="... until this many frames: then not estimated (`offset_s` kept)")
    search_s: float = Field(0.1, gt=0, le=0.5, description="the offsets searched: within +- this")
    max_uncertainty_s: float = Field(
        0.005, gt=0, le=0.1, description="the estimate is trusted when its bootstrap spread over the frame pairs is "
        "at most this")
    max_extrapolation_s: float = Field(
        0.05, ge=0, le=0.5, description="a negative offset reads the device after its newest pose: its last motion "
        "continues at constant velocity at most this long (a live frame cannot wait for the next pose)")
