"""SlamConfig: every knob of the SLAM engine, typed and validated, with the paper's defaults and named presets.

Sections follow the system's parts: `frontend` (model, image size, submaps, keyframes), `tracking`
(the pose source and the geometric ones), `depth` (multi-view depth for frames without depth), `loop` (detection,
relocalization, pose graph), `mapping` (voxelization, fusion, refinement) and `input` (how given depth and poses
are used). `SlamConfig.preset(name)` gives "paper" (the paper's settings), "default" (paper settings with the
default model), "fast" (CPU-friendly), "rgbd" (RGB-D input on a CPU) and "test" (tiny and quick, for unit tests).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from worker.data.registration_config import DepthCameraConfig
from worker.depth.config import MultiViewDepthConfig
from worker.tracking.photos.config import PhotoRegistrationConfig
from worker.tracking.rgbd_config import RgbdOdometryConfig
from worker.tracking.seeded_config import DeviceClockConfig, DevicePoseConfig, PoseChoiceConfig
from worker.tracking.vo_config import VisualOdometryConfig

log = logging.getLogger(__name__)

DEFAULT_CHECKPOINT = Path(__file__).parent / "frontend" / "weights" / "tiny.safetensors"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class FrontendConfig(_Section):
    """The feed-forward model and submap tracking (paper 4.1, ablation 5.5)."""

    model: str = Field("tiny", description="model config name for worker.frontend.build_model")
    checkpoint: str | None = Field(None, description="safetensors checkpoint; None = the shipped default if present")
    long_side: int = Field(224, ge=32, le=2048, multiple_of=16,
                           description="images are resized so the long side is this, then cropped to /16")
    submap_size: int = Field(8, ge=2, le=256, description="frames per submap")
    submap_overlap: Literal[1] = Field(1, description="frames shared by consecutive submaps (the paper's one)")
    keyframe_every: int = Field(
        4, ge=1, description="engine-chosen keyframes (posed, RGB-D odometry): a keyframe at least every N frames")
    keyframe_depth_ratio: float = Field(
        0.10, gt=0, description="monocular: a keyframe once the camera moved this fraction of the scene depth")
    keyframe_translation: float = Field(
        0.2, gt=0, description="keyframe selectors without a scene-depth rule: or when it moved this far (pose "
        "units); engine-chosen keyframes never use it (until a scene depth is known, turns and keyframe_every make "
        "them, the same in any pose units)")
    keyframe_parallax: float = Field(
        0.08, gt=0, description="engine-chosen keyframes: or once the camera moved this fraction of the scene depth "
        "(the median depth of the last keyframe: sensor, or the newest multi-view depth)")
    keyframe_min_overlap: float = Field(
        0.7, ge=0, lt=1, description="engine-chosen keyframes: or once less than this fraction of the last "
        "keyframe's view (a grid of its pixels at their depth) is inside the frame; 0 = not judged")
    keyframe_approach: float = Field(
        0.1, ge=0, lt=1, description="engine-chosen keyframes: or once the camera came this fraction of their depth "
        "closer to the last keyframe's view (driving forward: what it saw from afar is now seen magnified); 0 = not "
        "judged")
    keyframe_rotation_deg: float = Field(15.0, gt=0, description="or turned this much")
    keyframe_blur_ratio: float = Field(
        0.5, ge=0, lt=1, description="a due keyframe waits (up to keyframe_blur_delay frames) while the frame's "
        "sharpness (variance of the Laplacian) is below this fraction of the recent frames' median; 0 = never")
    keyframe_blur_delay: int = Field(2, ge=0, le=16, description="frames a keyframe may wait for a sharper frame")
    min_confidence: float = Field(1.5, ge=1.0, description="per-pixel confidence below which surfels are dropped")
    min_kept_fraction: float = Field(
        0.0, ge=0.0, le=1.0, description="monocular: when fewer pixels pass min_confidence, keep this fraction "
        "(the most confident) so a model with poorly calibrated confidence still maps")
    ray_aligned_surfels: bool = Field(
        True, description="monocular: each surfel on its pixel's ray (given or estimated intrinsics) at the "
        "predicted depth; False = the predicted 3D point as is (the paper)")
    seed: int = Field(0, description="seed of the randomly initialised model when no checkpoint exists")



class LoopConfig(_Section):
    """Loop detection, relocalization and Sim(3) pose-graph optimisation (paper 4.2)."""

    enabled: bool = True
    descriptor: Literal["encoder", "orb"] = "orb"
    relocalization: Literal["hidden_state", "pnp"] = Field(
        "hidden_state", description="hidden_state = f(I_j, M_a) (paper); pnp needs depth (given or predicted)")
    top_k: int = Field(5, ge=1, description="candidates verified per keyframe")
    shortlist: int = Field(
        10, ge=1, description="ORB: keyframes scored geometrically per query, the inverted index's best (bounds the "
        "cost per keyframe whatever the map size)")
    recent_candidates: int = Field(
        2, ge=0, description="ORB: of the shortlist, the newest keyframes outside the exclusion window, always scored")
    max_loops_per_keyframe: int = Field(
        1, ge=1, description="verified candidates of one keyframe that become loop edges (best first)")
    min_score: float = Field(0.03, ge=0.0, le=1.0, description="descriptor similarity needed to verify a candidate")
    exclusion_frames: int = Field(20, ge=0, description="keyframes this many frames back or closer are not candidates")
    min_inliers: int = Field(12, ge=4, description="PnP verification: inliers needed")
    xfeat_verification: bool = Field(
        True, description="PnP verification: a candidate with too few ORB matches or inliers (a revisit from a wide "
        "viewpoint change) is matched again by XFeat and verified the same way (source `pnp_xfeat`)")
    xfeat_min_inliers: int = Field(
        50, ge=12, description="... PnP inliers an XFeat match needs (more than ORB's: on ICL, 30-49 inliers gave "
        "a third of the poses 5-10 degrees off at 20-35 degree view changes)")
    xfeat_per_keyframe: int = Field(
        1, ge=0, description="... candidates of one keyframe verified by XFeat at most (a network pass per new "
        "keyframe image, ~25 ms at 320x240)")
    loop_weight: float = Field(1.0, gt=0, description="information weight of loop edges relative to odometry")
    robust_kernel: Literal["cauchy", "huber", "none"] = "cauchy"
    robust_k: float = Field(1.0, gt=0, description="robust kernel threshold on the whitened loop residual")
    # Visual odometry (RGB only) on TUM fr1/xyz (bench/journal/62): its scale drifts (27 % over 62 keyframes without
    # loops), its loops' translations are off by ~3.5 % of the scene depth and their scales by ~4.5 % (median, 148
    # loops against the motion capture), and robust_k 1 cuts correct loops with the drift. `monocular_robust_k` 3,
    # `monocular_scale_sigma` 0.03 and loop sigmas 0.04 / 0.05 take TUM's 1.98 cm to 1.68 but ICL at 320x240 from
    # 1.78 to 1.95 cm (-0.9 dB): the defaults keep the metric modes' graph until a setting gains on both.
    monocular_robust_k: float = Field(
        1.0, gt=0, description="visual odometry sessions: robust_k for their loop edges")
    monocular_scale_sigma: float = Field(
        0.01, gt=0, le=1, description="visual odometry sessions: standard deviation of the log-scale change along "
        "one odometry edge between keyframes (monocular scale drifts)")
    monocular_loop_translation_sigma: float = Field(
        0.02, gt=0, le=1, description="visual odometry sessions: a loop edge's translation standard deviation "
        "(scene length units; its points come from multi-view stereo depth)")
    monocular_loop_scale_sigma: float = Field(
        0.02, gt=0, le=1, description="visual odometry sessions: a loop edge's log-scale standard deviation")
    pgo_iterations: int = Field(50, ge=1, le=10000)
    loop_cooldown_keyframes: int = Field(2, ge=0, description="keyframes between two accepted loop closures")
    depth_alignment: bool = Field(
        True, description="posed RGB-D: refine each loop edge by ICP on the two keyframes' depth")
    alignment_min_inliers: float = Field(0.3, ge=0, le=1, description="ICP: fraction of points with a close match")
    alignment_max_rms: float = Field(
        0.005, gt=0, description="ICP: largest RMS point-to-plane residual, in scene length units (the median depth "
        "of the first keyframe with depth; ICL, 1.85 m: 0.9 cm), so that it holds in any pose units")
    covisible_neighbours: int = Field(
        4, ge=0, le=32, description="RGB-D and posed RGB-D sessions (not pose_mode fixed): each new keyframe is "
        "aligned densely (intensity and depth, as RGB-D odometry aligns frames) to this many of the older keyframes "
        "its pose puts nearest; each fit is a `covisible` pose-graph edge and the graph is solved "
        "(`drift_corrected`, source covisibility). 0 = off. TUM fr1/xyz RGB-D: ATE 1.25 -> 1.19 cm, keyframes "
        "1.15 -> 0.96 cm, 21.4 -> 22.6 dB; held-out fr1/rpy 2.33 -> 1.78 cm, 18.4 -> 21.2 dB (bench/RESULTS.md)")
    covisible_distance: float = Field(
        0.3, gt=0, description="... older keyframes at most this far from it (scene length units) ...")
    covisible_rotation_deg: float = Field(20.0, gt=0, le=180, description="... and turned at most this much")
    covisible_min_overlap: float = Field(
        0.5, gt=0, le=1, description="... kept when this share of the older keyframe's surface is found again ...")
    covisible_max_residual: float = Field(
        0.01, gt=0, description="... with a robust depth residual at most this (scene length units) ...")
    covisible_max_photometric: float = Field(
        0.12, gt=0, description="... and a robust intensity residual at most this (0..1 scale; RGB-D odometry's "
        "`max_photometric_residual`): an alignment that slid along a flat surface fits its depth, not its image")


class MappingConfig(_Section):
    """The 2DGS backend (paper 4.3)."""

    enabled: bool = True
    process: bool = Field(
        False, description="map in a process of its own beside tracking (worker.pipeline.mapping_process): "
        "tracking keeps an interpreter to itself; threaded sessions only, not with the model's hole filling")
    voxel_block: Literal[1, 2] = Field(2, description="2 = merge 2x2 blocks (eq. 15-16); 1 = keep every pixel")
    merged_scale_factor: float = Field(
        2.0, gt=0, description="scale multiplier of a merged block's surfel: a 2x2 block covers twice the width")
    tau_depth: float = Field(0.05, gt=0, description="relative depth range above which a block is not merged")
    tau_accum: float = Field(0.7, gt=0, le=1.0, description="add new surfels only where accumulation < tau_accum")
    prune: bool = Field(True, description="prune surfels that explain a new keyframe badly (paper 4.3)")
    prune_multiview: bool = Field(
        True, description="prune, whatever `prune` says, in sessions whose keyframe depth comes from multi-view "
        "stereo (no depth sensor): stereo leaves surfels at wrong depths that cover the next keyframes' views, and "
        "new surfels are added only where the map is thin (KITTI RGB only, the map before the final refinement: "
        "13.0 -> 14.8 dB)")
    prune_rgb_error: float = Field(0.25, gt=0, description="prune surfels on pixels with this L1 colour error")
    prune_depth_error: float = Field(0.1, gt=0, description="... or this relative depth error")
    refine_keyframes: int = Field(5, ge=1, description="K: refine the surfels of the last K keyframes")
    refine_iterations: int = Field(20, ge=0, le=10000, description="iterations after each keyframe")
    ssim_weight: float = Field(0.2, ge=0, le=1)
    depth_weight: float = Field(0.1, ge=0)
    archived_images: int = Field(
        0, ge=0, description="keyframe images kept beyond the window (JPEG, half-size depth, 0.06 MB at 320x240) for "
        "refinement; when more keyframes have left the window, the most redundant views are let go, one at a time "
        "(the keyframe whose nearest held keyframe sees most nearly the same view; 0 = keep only the window's)")
    archived_views_per_refine: int = Field(
        0, ge=0, description="each keyframe's refinement also trains this many random archived keyframes (and their "
        "surfels), so the live map keeps the views the window has left")
    final_refine_passes: int = Field(
        0, ge=0, le=1000, description="refinement at finish(): passes over every keyframe whose image is held "
        "(window + archive), one iteration per keyframe per pass, in a seeded random order")
    final_refine_lr_end: float = Field(
        0.3, gt=0, le=1, description="the final refinement's learning rates fall geometrically to this factor of "
        "the keyframe refinement's over its iterations, or over its time budget where that ends it first (1: "
        "constant). ICL 320x240, held-out PSNR against constant rates: RGB-D 30.36 dB against 29.36 +- 0.25 over "
        "four view orders, posed RGB 29.15 against 28.77-28.83, RGB only 29.03 against 28.49-28.55 (bench/RESULTS.md)")
    final_refine_poses: bool = Field(
        True, description="the final refinement also refines the camera of each held keyframe but the oldest (which "
        "holds the map's frame) against its photo, with the surfels (photometric bundle adjustment), and every "
        "frame moves with the keyframes before and after it (a `poses_refined` revision); never with pose_mode "
        "fixed. Held-out PSNR, ICL 320x240 (clean clone): RGB only 29.03 -> 29.29 dB, posed RGB 28.97 -> 29.47, "
        "RGB-D +0.08; KITTI 00 60 frames: RGB +0.14, posed RGB +0.12 (bench/RESULTS.md)")
    final_refine_seed: int = Field(
        0, ge=0, description="seed of the final refinement's random view order (benchmarks vary it to measure how "
        "far a figure moves with the order alone)")
    final_refine_budget_s: float = Field(
        25.0, ge=0, description="finish(): the final refinement stops once finish() has taken this many seconds "
        "(draining the stages included) whatever its passes (0 = no bound), so finishing a session stays bounded")
    final_refine_budget_counts_drain: bool = Field(
        True, description="finish(): final_refine_budget_s counts from the start of finish(), draining the stages "
        "included (a live session's whole finish is bounded), or, false, from the start of the final refinement "
        "(an offline run: its drain maps keyframes it must map anyway, and the refinement keeps its budget)")
    close_holes: bool = Field(
        True, description="the final refinement first closes the holes of every held keyframe's view, widened by "
        "hole_margin past its border, from the map's own geometry (worker.mapping.hole_closing)")
    hole_margin: float = Field(
        0.1, ge=0, le=1, description="close_holes: fraction of the image's width and height the view is widened by "
        "on every side (views between keyframes see past the keyframes' borders)")
    background: bool = Field(
        True, description="sessions whose keyframe depth comes from multi-view stereo: renders and refinement show, "
        "behind the surfels, the colour keyframes saw in each world direction where the map left them uncovered "
        "(the sky; surfaces stereo gave no depth), instead of black (worker.mapping.background); depth and coverage "
        "stay the surfels' own. Sensor depth leaves few such places, and there it cost live RGB-D 0.4 dB (ICL at 30 "
        "frames/s) for +0.08 offline: off for them")
    idle_refine: bool = Field(
        True, description="a threaded mapping stage with an empty queue refines the keyframes whose refinement load "
        "shedding cut, oldest first (the live map catches up when the camera slows down)")
    voxel_cap: int = Field(
        64, ge=0, description="surfels per world voxel at most; a revisited voxel takes new surfels only from a "
        "clearly finer view (0 = no cap)")
    shed_backlog: int = Field(
        2, ge=0, description="load shedding: with more keyframes than this waiting, each keyframe's refinement "
        "shrinks in proportion (iterations x shed_backlog / backlog) and trains no archived views; 0 = never shed")
    merge_only_backlog: int = Field(
        6, ge=1, description="load shedding: with more keyframes than this waiting, keyframes are merged into the "
        "map without refinement (finish() refines them)")
    exposure: bool = Field(
        True, description="estimate each keyframe's exposure (a gain per colour channel) against the rest of the "
        "map when it is merged, before its catch-up refinement and before the final refinement, and keep it out of "
        "the map's colours: renders show exposure-normalised colours")
    exposure_prior: float = Field(
        0.002, ge=0, description="exposure: weight of the identity gain against the fitted one")
    exposure_threshold: float = Field(
        0.03, ge=0, le=0.5, description="exposure: estimated log-gain changes within this are shrunk to none, larger "
        "ones nearly kept (view-dependent shading alone makes a keyframe's median brightness differ by up to 2 % "
        "from the map on ICL; normalising that away compounds from keyframe to keyframe)")
    exposure_channels: Literal["shared", "per_channel"] = Field(
        "shared", description="exposure: one gain for the three channels (an exposure change), or a gain per channel "
        "(also white balance; on real footage whose colours are steady the per-channel gains drifted apart from "
        "keyframe to keyframe, turning the map's colours: -2 to -3 dB on an iPhone and a RealSense sequence)")


class InputConfig(_Section):
    """How optional per-frame inputs are used (posed and RGB-D modes)."""

    use_depth: bool = Field(True, description="frames carrying depth: surfel means from unprojected depth")
    pose_mode: Literal["auto", "ignore", "prior", "fixed", "seeded"] = Field(
        "auto", description="frames carrying poses: ignore them, use them as the odometry (priors in PGO), keep them "
        "(fixed), or seeded: RGB-D / visual odometry tracks from the device's motion, the device poses are "
        "pose-graph priors (`device_poses`) and their jumps are detected. auto: seeded with depth; without, prior "
        "where the device poses agree with the images, else seeded (`pose_choice`; on ICL visual odometry does not "
        "beat the exact poses, on KITTI it beats the GPS/IMU ones; RGB-D odometry does beat drifting ones)")
    device_poses: DevicePoseConfig = Field(default_factory=DevicePoseConfig,
                                           description="pose_mode seeded: the device poses' uncertainty and jumps")
    pose_choice: PoseChoiceConfig = Field(
        default_factory=PoseChoiceConfig, description="pose_mode auto without depth: prior or seeded, chosen by how "
        "well the device poses agree with the images over the first frames (a `pose_source_chosen` event)")
    device_clock: DeviceClockConfig = Field(
        default_factory=DeviceClockConfig, description="frames carrying poses: the device pose clock's offset from "
        "the camera's, estimated from the images or given (`worker.tracking.device_clock`)")
    depth_camera: DepthCameraConfig | None = Field(
        None, description="the depth camera's intrinsics and depth-to-colour extrinsic: depth is registered to the "
        "colour camera before use (worker.data.registration); without it, misregistration is detected and reported")
    detect_misregistration_frames: int = Field(
        5, ge=0, le=100, description="without depth_camera: frames with depth whose depth and colour edges are "
        "compared to detect a misregistration (0: off)")
    surfel_init: Literal["model", "depth"] = Field(
        "model", description="with depth: other surfel attributes from the model, or initialised from image+depth")
    depth_scale_to_pose: bool = Field(True, description="monocular with poses: scale model depth to the poses")
    depth_source: Literal["auto", "mvs", "model"] = Field(
        "auto", description="frames without depth: surfels from multi-view stereo on the tracked poses (mvs) or from "
        "the learned model; auto = the model when it tracks, else mvs")
    mvs_frames_after: int = Field(
        4, ge=0, le=64, description="mvs: frames a keyframe waits for, so that it has neighbours on both sides")
    mvs_buffer_frames: int = Field(16, ge=2, le=256, description="mvs: recent frames kept as neighbour candidates")
    # propagate: +0.5 dB and a third fewer uncovered pixels on real sparse photos (the fox orbit), neutral on ICL
    mvs_fill: Literal["none", "model", "propagate"] = Field(
        "propagate", description="mvs: pixels without a confident depth get no surfel (none), the learned model's "
        "single-view depth scaled to the confident pixels (model; one model pass per keyframe), or a depth "
        "propagated from confident pixels of similar colour on the same plane (propagate: worker.depth.hole_fill; "
        "those surfels start less opaque)")
    mvs_planes: bool = Field(
        True, description="mvs with propagate: holes of image regions lying on a dominant plane of the recent "
        "keyframes' confident points (a uniform floor or wall) take that plane's depth (worker.depth.world_planes)")
    # A real iPhone LiDAR walk along a plain wall: posed RGB keyframe depth 2.49 cm at 62.0 % -> 2.53 cm at 77.0 %
    mvs_border_planes: bool = Field(
        True, description="mvs with planes: a large textureless region without supported pixels (a plain wall) "
        "takes the plane its border points lie on, parallel or perpendicular to a dominant plane "
        "(worker.depth.border_planes)")


class TrackingConfig(_Section):
    """The pose source and the settings of the geometric ones."""

    source: Literal["auto", "device", "rgbd_odometry", "visual_odometry", "photos", "model"] = Field(
        "auto", description="pose source: auto = the frames' poses when they carry them, else RGB-D odometry with "
        "depth, else visual odometry for video and photo registration for photos (`photos.min_interval_s`; the "
        "learned model instead of the odometries when a model other than the shipped synthetic one is "
        "configured); photos = photo registration (incremental structure from motion) whatever the frame rate")
    rgbd: RgbdOdometryConfig = Field(default_factory=RgbdOdometryConfig)
    visual: VisualOdometryConfig = Field(default_factory=VisualOdometryConfig)
    photos: PhotoRegistrationConfig = Field(default_factory=PhotoRegistrationConfig)
    max_side: int = Field(
        0, ge=0, le=8192, description="the tracking resolution: frames whose long side is larger are tracked at this "
        "long side (aspect kept; mapping keeps the full frame); 0 = as they come")


class SlamConfig(_Section):
    """The whole engine's configuration. `SlamConfig.preset(name, **overrides)` builds a named one."""

    name: str = "default"
    frontend: FrontendConfig = Field(default_factory=FrontendConfig)
    loop: LoopConfig = Field(default_factory=LoopConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    input: InputConfig = Field(default_factory=InputConfig)
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)
    depth: MultiViewDepthConfig = Field(default_factory=MultiViewDepthConfig)
    threaded: bool = Field(
        True, description="tracking, mapping and loop closing in their own threads; False = inline, deterministic")
    queue_size: int = Field(
        24, ge=1, le=1024, description="the mapping stage's keyframe backlog: keyframes waiting beyond it are "
        "dropped from the map, oldest first (tracking never waits for mapping)")
    device: str = Field("cpu", pattern=r"^(cpu|cuda(:\d+)?)$")
    num_threads: int = Field(2, ge=1, le=256, description="torch intra-op threads")

    @model_validator(mode="before")
    @classmethod
    def _pose_source_moved(cls, data: Any) -> Any:
        """`frontend.tracking` (configs and snapshots of earlier versions) is `tracking.source` now."""
        if isinstance(data, dict) and isinstance(data.get("frontend"), dict) and "tracking" in data["frontend"]:
            frontend = dict(data["frontend"])
            tracking = dict(data.get("tracking") or {})
            tracking.setdefault("source", frontend.pop("tracking"))
            data = {**data, "frontend": frontend, "tracking": tracking}
        return data

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> SlamConfig:
        """A named preset ("paper", "default", "fast", "rgbd", "test") with optional nested overrides
        (e.g. `mapping={"refine_iterations": 5}`)."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
        data = deep_merge(PRESETS[name], overrides)
        data["name"] = overrides.get("name", name)
        return cls.model_validate(data)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SlamConfig:
        """Validate a plain dict, raising ValueError with pydantic's message on bad values."""
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise ValueError(f"invalid SLAM config: {err}") from err

    def checkpoint_path(self) -> Path | None:
        """The checkpoint to load: the configured one, else the shipped default when present, else None
        (a seeded random model is then used, with a warning)."""
        if self.frontend.checkpoint:
            path = Path(self.frontend.checkpoint)
            if not path.is_file():
                raise ValueError(f"checkpoint {path} does not exist")
            return path
        if self.frontend.model == "tiny" and DEFAULT_CHECKPOINT.is_file():
            return DEFAULT_CHECKPOINT
        return None


def deep_merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """`base` with `overrides` merged in, section by section (nested dicts merged, other values replaced)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for key, value in overrides.items():
        if isinstance(value, BaseModel):
            value = value.model_dump()
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


PRESETS: dict[str, dict[str, Any]] = {
    # The paper: 512-wide images, paper-size model, K=5 keyframes x 20 iterations.
    "paper": {"frontend": {"model": "paper", "long_side": 512, "ray_aligned_surfels": False}, "device": "cuda"},
    # Paper settings with the shipped default model on whatever device is there; that model's confidence is not
    # calibrated yet (most pixels stay near 1), so the most confident 30 % of each keyframe is mapped regardless.
    "default": {"frontend": {"min_kept_fraction": 0.3}},
    # CPU-friendly: smaller images and fewer refinement iterations.
    # With RGB-D input its surfels come from the depth and image alone: no 2DGS-head pass, and maps that do not
    # depend on the frontend's weights (the default until trained weights ship).
    "fast": {"frontend": {"long_side": 224, "keyframe_every": 6, "min_kept_fraction": 0.3},
             "mapping": {"refine_keyframes": 3, "refine_iterations": 8},
             "input": {"surfel_init": "depth"}},
    # Posed RGB-D on a CPU (measured on ICL, bench/slam.py): surfels from the depth, 2x2 merged, no pruning (it
    # cut holes that later keyframes do not refill: -4 dB on ICL), new surfels wherever the map covers a pixel
    # less than 95 %, 5 refinement iterations over the last 2 keyframes; at finish(), 8 passes of refinement over
    # every keyframe (up to 64 archived images): 23.4 -> 28.9 dB on ICL. (Per-pixel surfels are 0.1 dB better
    # before the final refinement, 0.3 dB worse after it, and 3x as many.) Each keyframe's refinement also trains 2
    # random archived keyframes: the live map (before finish) 23.4 -> 24.7 dB for 12 % more refinement time.
    "rgbd": {"frontend": {"long_side": 224, "keyframe_every": 6},
             "mapping": {"voxel_block": 2, "prune": False, "tau_accum": 0.95, "refine_keyframes": 2,
                         "refine_iterations": 5, "archived_images": 64, "archived_views_per_refine": 2,
                         "final_refine_passes": 8},
             "input": {"surfel_init": "depth"}},
    # Unit tests: tiny images, few iterations, single-threaded and deterministic.
    "test": {"frontend": {"long_side": 64, "submap_size": 4, "keyframe_every": 2},
             "loop": {"exclusion_frames": 12, "pgo_iterations": 30},
             "mapping": {"refine_keyframes": 2, "refine_iterations": 3, "idle_refine": False},
             "threaded": False, "queue_size": 4, "num_threads": 1},
}
