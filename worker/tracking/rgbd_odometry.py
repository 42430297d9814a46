"""RGB-D odometry as a pose source: each frame densely aligned to a reference keyframe (worker.tracking.
dense_alignment), seeded by constant velocity and, where it disagrees, also by a feature-based PnP guess
(worker.tracking.feature_seed; the better-fitting alignment wins); the reference moves on when the view has changed
enough.

Keyframes are reused when the camera comes back: the engine's keyframes are kept (compact) as places; when the
reference must move on and a place at least `reuse_min_age` frames old lies near the camera, the frame is aligned to
it and, when it overlaps well, that place becomes the reference instead of a new one. Its pose is re-anchored to the
frame's (no jump: drift is for loop closure to correct), and frames that see it well ask for no new keyframe
(`keyframe_hint=False`): a room walked through again and again keeps the keyframes of its first visit. Each frame
tracked against such a place carries it as its `anchor`: at the session's end the frame is put on the place's
corrected pose (TUM fr1/xyz: 1.19 -> 0.89 cm over all frames).

Frames without intrinsics: tracking starts with a typical focal length; once the camera has moved enough (or after
`calibration_frames` frames) the focal length is estimated from those frames (worker.tracking.focal_calibration),
they are tracked again with it, and an `initialized` event carries their new poses and the camera found.

Tracking is declared lost when an alignment is ill-posed (too little depth or texture), overlaps the reference too
little, or leaves large residuals; the pose then stays at the last good one (never a jump) and every following frame
is tried against the reference keyframes kept in a small ring, from the last good pose, until one fits again
(`relocalized`).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.data.sharpness import sharpness
from worker.events import Initialized, Relocalized, TrackingLost
from worker.geometry import Intrinsics
from worker.tracking.base import TrackingResult
from worker.tracking.dense_alignment import (
    AlignmentResult,
    AlignmentSettings,
    Backend,
    PyramidLevel,
    align,
    build_pyramid,
    kernels,
)
from worker.tracking.feature_seed import KeypointSet, detect, pnp_seed
from worker.tracking.focal_calibration import estimate_focal
from worker.tracking.motion import motion_model_pose, relative_motion
from worker.tracking.rgbd_config import RgbdOdometryConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OdometryCheckpoint:
    """What tracking one frame may change (`RgbdOdometry.checkpoint`): restored, the frame is tracked again as if
    for the first time (a place a come-back re-anchored gets its pose back)."""

    references: tuple
    place_poses: tuple
    last_pose: np.ndarray | None
    previous_pose: np.ndarray | None
    lost: bool
    last_overlap: float
    typical_residual: float
    last_alignment: AlignmentResult | None


class _Current:
    """The frame being tracked: its pyramid and, computed on first use, its keypoints."""

    def __init__(self, pyramid: list[PyramidLevel], grey: np.ndarray) -> None:
        self.pyramid, self.grey = pyramid, grey
        self._keypoints: KeypointSet | None = None

    def keypoints(self) -> KeypointSet:
        if self._keypoints is None:
            self._keypoints = detect(_u8(self.grey))
        return self._keypoints


def _u8(grey: np.ndarray) -> np.ndarray:
    return np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _differs(a: np.ndarray, b: np.ndarray, translation: float, rotation_deg: float = 2.0) -> bool:
    moved, turned = relative_motion(a, b)
    return moved > translation or turned > rotation_deg


def _best(results: list[AlignmentResult]) -> AlignmentResult:
    """The well-posed alignment with the smallest photometric residual (the first one when none is well posed)."""
    usable = [r for r in results if r.ok]
    return min(usable, key=lambda r: r.photometric_rms) if usable else results[0]


def grey_of(image: np.ndarray) -> np.ndarray:
    """float32 intensity in [0, 1] from uint8 RGB."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0


class _Reference:
    """A reference keyframe: its pose and the RGB-D data alignment needs (rebuilt into a pyramid on demand)."""

    def __init__(self, index: int, pose: np.ndarray, grey: np.ndarray, depth: np.ndarray, reused: bool = False,
                 pyramid: list[PyramidLevel] | None = None) -> None:
        self.index, self.pose, self.grey, self.depth = index, pose, grey, depth
        self.reused = reused  # a place come back to (frames that see it well need no keyframe)
        valid = depth[depth > 0]
        self.median_depth = float(np.median(valid)) if valid.size else 1.0
        self._pyramid = pyramid  # the tracked frame's own pyramid when it becomes the reference
        self._keypoints: KeypointSet | None = None
        self._sharpness: float | None = None

    @property
    def sharpness(self) -> float:
        if self._sharpness is None:
            self._sharpness = sharpness(self.grey)
        return self._sharpness

    def pyramid(self, K: np.ndarray, levels: int, backend: Backend = "auto") -> list[PyramidLevel]:
        if self._pyramid is None:
            self._pyramid = build_pyramid(self.grey, self.depth, K, levels, backend=backend)
        return self._pyramid

    def keypoints(self, K: np.ndarray, levels: int) -> KeypointSet:
        if self._keypoints is None:
            self._keypoints = detect(_u8(self.grey), self.pyramid(K, levels)[0].points)
        return self._keypoints

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "pose": self.pose, "grey": (self.grey * 255).round().astype(np.uint8),
                "depth": self.depth.astype(np.float16), "reused": self.reused}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> _Reference:
        return cls(int(d["index"]), np.asarray(d["pose"], np.float64),
                   np.asarray(d["grey"], np.uint8).astype(np.float32) / 255.0, np.asarray(d["depth"], np.float32),
                   bool(d.get("reused", False)))


class _Place:
    """An engine keyframe kept to come back to: pose, grey uint8 and depth float16 (a quarter of a reference)."""

    def __init__(self, index: int, pose: np.ndarray, grey: np.ndarray, depth: np.ndarray) -> None:
        self.index, self.pose = index, np.asarray(pose, np.float64)
        self.grey, self.depth = np.asarray(grey, np.uint8), np.asarray(depth, np.float16)
        valid = self.depth[self.depth > 0]
        self.median_depth = float(np.median(valid)) if valid.size else 1.0

    def reference(self, pose: np.ndarray) -> _Reference:
        return _Reference(self.index, pose, self.grey.astype(np.float32) / 255.0, self.depth.astype(np.float32),
                          reused=True)

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "pose": self.pose, "grey": self.grey, "depth": self.depth}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> _Place:
        return cls(int(d["index"]), d["pose"], d["grey"], d["depth"])


class RgbdOdometry:
    """Pose source for frames with depth and no poses (see the module docstring)."""

    name = "rgbd_odometry"

    def __init__(self, config: RgbdOdometryConfig | None = None) -> None:
        self.config = config or RgbdOdometryConfig()
        c = self.config
        self.settings = AlignmentSettings(iterations=tuple(c.iterations), max_points=c.max_points,
                                          photometric_weight=c.photometric_weight)
        kernels(self.settings.backend)  # builds (or loads) the compiled kernels now, not on the first tracked frame
        self.references: deque[_Reference] = deque(maxlen=c.reference_ring)
        self.places: deque[_Place] = deque(maxlen=max(1, c.reuse_keyframes))  # engine keyframes to come back to
        self.last_pose: np.ndarray | None = None
        self.previous_pose: np.ndarray | None = None
        self.lost = False
        self.last_overlap = 1.0
        self.typical_residual = self.config.max_photometric_residual  # running mean of accepted alignments
        self.last_alignment: AlignmentResult | None = None  # the fit of the last accepted alignment
        self.estimated_intrinsics: Intrinsics | None = None  # only when frames come without intrinsics
        self.calibrating = False  # tracking with a guessed focal length until it is estimated
        self._calibration: list[tuple[int, np.ndarray, np.ndarray]] = []  # (index, grey, depth) since the start

    @property
    def reference(self) -> _Reference | None:
        return self.references[-1] if self.references else None

    def track(self, frame: Frame, intrinsics: Intrinsics | None, motion_guess: np.ndarray | None = None
              ) -> TrackingResult:
        """Track `frame`; `motion_guess` (previous^-1 @ current, e.g. a device's relative motion) replaces the
        constant-velocity guess when given."""
        if frame.depth is None:
            raise ValueError(f"frame {frame.index} has no depth: RGB-D odometry needs depth on every frame")
        if intrinsics is None and self.estimated_intrinsics is None:
            self.calibrating = self.config.self_calibrate
        K, grey, depth = self._inputs(frame, intrinsics)
        result = self._track(frame.index, grey, depth, K, motion_guess)
        if self.calibrating and result.tracked:
            return self._calibration_step(frame, grey, depth, result)
        return result

    def checkpoint(self) -> OdometryCheckpoint:
        """The state one frame's tracking may change, to track that frame again from another guess (`restore`)."""
        return OdometryCheckpoint(tuple(self.references), tuple((p, p.pose) for p in self.places), self.last_pose,
                                  self.previous_pose, self.lost, self.last_overlap, self.typical_residual,
                                  self.last_alignment)

    def restore(self, checkpoint: OdometryCheckpoint) -> None:
        """Back to the state of `checkpoint` (taken on this odometry since its last snapshot load)."""
        self.references = deque(checkpoint.references, maxlen=self.config.reference_ring)
        for place, pose in checkpoint.place_poses:
            place.pose = pose
        self.last_pose, self.previous_pose = checkpoint.last_pose, checkpoint.previous_pose
        self.lost, self.last_overlap = checkpoint.lost, checkpoint.last_overlap
        self.typical_residual, self.last_alignment = checkpoint.typical_residual, checkpoint.last_alignment

    def resume_from(self, frame: Frame, intrinsics: Intrinsics | None, pose: np.ndarray,
                    min_sharpness_ratio: float = 0.0, restart: bool = True) -> TrackingResult:
        """Track `frame` again (after `track` lost it), knowing from outside (a device pose) that the camera is
        near `pose`: aligned to the newest reference from there, else, when that fails too, a new reference at
        `pose` (the odometry restarts where the device says the camera is; no velocity across the seam).
        `relocalized` (method `device_pose`, with the alignment's failure as `reason`) reports the restart. No
        restart on a frame less sharp than `min_sharpness_ratio` times the reference (motion blur: a blurred
        reference would lose the next frames too), nor with `restart` False: it stays lost, relocalising from `pose`
        on the next frame."""
        if self.reference is None or self.calibrating:
            return self.track(frame, intrinsics)
        K, grey, depth = self._inputs(frame, intrinsics)
        current = _Current(build_pyramid(grey, depth, K, self.config.pyramid_levels, backend=self.settings.backend),
                           grey)
        self.lost = False
        aligned, reason = self._align_to(self.reference, current, pose, K)
        if aligned is not None:
            self._advance(aligned)
            self._maybe_new_reference(frame.index, grey, depth, aligned, current, K)
            return TrackingResult(aligned, depth=depth, keyframe_hint=self._covered_hint())
        pose = np.asarray(pose, np.float64).copy()
        if (not restart or np.count_nonzero(depth) <= 0.2 * depth.size
                or sharpness(grey) < min_sharpness_ratio * self.reference.sharpness):
            self.lost, self.previous_pose, self.last_pose = True, None, pose
            return TrackingResult(pose.copy(), tracked=False, keyframe_hint=False)
        self.previous_pose, self.last_pose = None, pose
        self.references.append(_Reference(frame.index, pose, grey, depth, pyramid=current.pyramid))
        self.last_overlap = 1.0
        log.info("frame %d: RGB-D odometry restarted at the device's pose (%s)", frame.index, reason)
        return TrackingResult(pose.copy(), depth=depth,
                              events=[Relocalized(method="device_pose", reason=reason)])

    def _inputs(self, frame: Frame, intrinsics: Intrinsics | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """K, grey image and cleaned depth (no NaN, no negative) of a frame."""
        intrinsics = intrinsics or self._guess_intrinsics(frame)
        K = intrinsics.matrix().numpy().astype(np.float64)
        depth = np.nan_to_num(np.asarray(frame.depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        depth[depth < 0] = 0.0
        return K, grey_of(frame.image), depth

    def _track(self, index: int, grey: np.ndarray, depth: np.ndarray, K: np.ndarray,
               motion_guess: np.ndarray | None = None) -> TrackingResult:
        if self.reference is None:
            return self._first(index, grey, depth)
        current = _Current(build_pyramid(grey, depth, K, self.config.pyramid_levels, backend=self.settings.backend),
                           grey)
        if self.lost:
            return self._relocalize(index, grey, depth, current, K)
        guess = (motion_model_pose(self.previous_pose, self.last_pose) if motion_guess is None
                 else self.last_pose @ motion_guess)
        reference = self.reference
        pose, reason = self._align_to(reference, current, guess, K)
        if pose is None:
            self.lost = True
            log.warning("frame %d: RGB-D tracking lost (%s)", index, reason)
            return TrackingResult(self.last_pose.copy(), tracked=False, keyframe_hint=False,
                                  events=[TrackingLost(reason=reason)])
        self._advance(pose)
        anchor = (reference.index, np.linalg.inv(reference.pose) @ pose) if reference.reused else None
        self._maybe_new_reference(index, grey, depth, pose, current, K)
        return TrackingResult(pose, depth=depth, keyframe_hint=self._covered_hint(), anchor=anchor)

    def _covered_hint(self) -> bool | None:
        """False (no keyframe) while the frame sees a place come back to well; else None (the engine decides)."""
        ref = self.reference
        if ref is not None and ref.reused and self.last_overlap >= self.config.reuse_overlap:
            return False
        return None

    def _calibration_step(self, frame: Frame, grey: np.ndarray, depth: np.ndarray, result: TrackingResult
                          ) -> TrackingResult:
        """Collect the frame; once the camera moved enough, estimate the focal length, re-track the collected
        frames with it and report them (`initialized`). No keyframes are asked for meanwhile."""
        c = self.config
        self._calibration.append((frame.index, grey, depth))
        first = self.references[0]
        moved, turned = relative_motion(first.pose, result.pose)
        enough = moved > c.calibration_motion * first.median_depth or turned > 10 * c.calibration_motion
        collected = len(self._calibration)
        if collected < c.calibration_frames and not (enough and collected >= c.calibration_frames // 3):
            result.keyframe_hint = False
            return result
        frames = self._calibration
        others = [frames[-1]] + ([frames[len(frames) // 2]] if len(frames) > 2 else [])
        guess = self.estimated_intrinsics
        estimate = estimate_focal([((frames[0][1], frames[0][2]), (g, d)) for _, g, d in others], guess.fx,
                                  (guess.cx, guess.cy), c.pyramid_levels)
        self.estimated_intrinsics = Intrinsics(estimate.focal, estimate.focal, guess.cx, guess.cy, guess.width,
                                               guess.height)
        self.calibrating = False
        self._calibration = []
        K = self.estimated_intrinsics.matrix().numpy().astype(np.float64)
        self.references.clear()
        self.last_pose = self.previous_pose = None
        poses = [[frames[0][0], self._first(*frames[0]).pose]]
        for index, g, d in frames[1:]:
            poses.append([index, self._track(index, g, d, K).pose])
        event = Initialized(frames=[[i, p.tolist()] for i, p in poses[:-1]],
                            intrinsics=self.estimated_intrinsics.to_dict(), focal_trusted=estimate.trusted)
        return TrackingResult(poses[-1][1], tracked=not self.lost, depth=depth, events=[event])

    def _guess_intrinsics(self, frame: Frame) -> Intrinsics:
        """A camera for frames without one: centred principal point, focal `focal_guess` x the long side (a
        typical phone or RGB-D camera); reported as the session's estimate."""
        if self.estimated_intrinsics is None or (self.estimated_intrinsics.width, self.estimated_intrinsics.height
                                                 ) != (frame.width, frame.height):
            focal = self.config.focal_guess * max(frame.width, frame.height)
            self.estimated_intrinsics = Intrinsics(focal, focal, frame.width / 2, frame.height / 2, frame.width,
                                                   frame.height)
            log.warning("RGB-D odometry without intrinsics: assuming a focal length of %.1f px", focal)
        return self.estimated_intrinsics

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The engine's keyframe becomes a place to come back to (when it has depth)."""
        if self.config.reuse_keyframes <= 0 or frame.depth is None:
            return
        depth = np.nan_to_num(np.asarray(frame.depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        if np.count_nonzero(depth > 0) > 0.2 * depth.size:
            self.places.append(_Place(frame.index, pose, _u8(grey_of(frame.image)), np.maximum(depth, 0.0)))

    # ------------------------------------------------------------------------------------------------ internals
    def _first(self, index: int, grey: np.ndarray, depth: np.ndarray) -> TrackingResult:
        """The first frame with depth anchors the world at its camera."""
        pose = np.eye(4)
        if not np.any(depth > 0):
            # Nothing to anchor the map to yet: wait at the origin for a frame with depth.
            return TrackingResult(pose, tracked=False, keyframe_hint=False,
                                  events=[TrackingLost(reason="no depth in the first frame")])
        self.references.append(_Reference(index, pose, grey, depth))
        self._advance(pose)
        return TrackingResult(pose, depth=depth)

    def _doubtful(self, result: AlignmentResult) -> bool:
        """Whether an alignment from the motion model may have settled in the wrong place: no velocity history yet,
        or it fits clearly worse than the recent ones (the feature seed is then tried too)."""
        c = self.config
        return (self.previous_pose is None or not result.ok or result.overlap < c.new_reference_overlap
                or result.photometric_rms > c.seed_residual_ratio * self.typical_residual)

    def _align_to(self, ref: _Reference, current: _Current, guess: np.ndarray, K: np.ndarray,
                  relocalizing: bool = False) -> tuple[np.ndarray | None, str]:
        """The current pose aligned to `ref` from `guess` (c2w), and from the feature seed where that alignment is
        doubtful (always when relocalizing) and the seed differs, or (None, why not). Outside relocalization a pose
        far from the motion model's guess is refused (a jump); relocalization may land anywhere near `ref`."""
        c = self.config
        T_init = np.linalg.inv(guess) @ ref.pose  # T_cur_ref
        reference = ref.pyramid(K, c.pyramid_levels, self.settings.backend)
        result = align(reference, current.pyramid, T_init, self.settings)
        if relocalizing or self._doubtful(result):
            seed = pnp_seed(ref.keypoints(K, c.pyramid_levels), current.keypoints(), K)
            if seed is not None and _differs(seed, T_init, c.seed_difference * ref.median_depth):
                result = _best([result, align(reference, current.pyramid, seed, self.settings)])
        self.last_overlap = result.overlap
        if not result.ok:
            return None, "too little depth or texture to align"
        if result.overlap < c.min_overlap:
            return None, f"the view overlaps the reference keyframe by {result.overlap:.0%} only"
        if result.photometric_rms > c.max_photometric_residual and not self._fits_geometry(result, ref):
            return None, f"large photometric residual ({result.photometric_rms:.3f})"
        pose = ref.pose @ np.linalg.inv(result.T)
        jump = float(np.linalg.norm(pose[:3, 3] - guess[:3, 3]))
        if jump > c.max_jump * ref.median_depth and not relocalizing:
            return None, f"the alignment jumped {jump:.2f} from the motion model"
        if result.photometric_rms <= c.max_photometric_residual:  # a blurred frame held by its depth is no norm
            self.typical_residual = 0.8 * self.typical_residual + 0.2 * result.photometric_rms
        self.last_alignment = result
        return pose, ""

    def _fits_geometry(self, result: AlignmentResult, ref: _Reference) -> bool:
        """Whether an alignment whose intensities fit poorly (motion blur, an exposure change) is still held by the
        depth: a small depth residual over a well-overlapping view, and intensities not beyond the blurred limit."""
        c = self.config
        return (result.photometric_rms <= c.blurred_photometric_residual
                and result.geometric_rms <= c.max_geometric_residual * ref.median_depth
                and result.overlap >= 0.8 * c.new_reference_overlap)

    def _relocalize(self, index: int, grey: np.ndarray, depth: np.ndarray, current: _Current,
                    K: np.ndarray) -> TrackingResult:
        for ref in reversed(self.references):
            pose, _ = self._align_to(ref, current, self.last_pose, K, relocalizing=True)
            if pose is not None and self.last_overlap >= self.config.new_reference_overlap * 0.8:
                self.lost = False
                self.previous_pose = None  # no velocity across the gap
                self.last_pose = pose
                log.info("frame %d: RGB-D tracking relocalized against keyframe %d", index, ref.index)
                self._maybe_new_reference(index, grey, depth, pose)
                return TrackingResult(pose, depth=depth,
                                      events=[Relocalized(keyframe=int(ref.index))])
        return TrackingResult(self.last_pose.copy(), tracked=False, keyframe_hint=False)

    def _advance(self, pose: np.ndarray) -> None:
        self.previous_pose, self.last_pose = self.last_pose, pose

    def _maybe_new_reference(self, index: int, grey: np.ndarray, depth: np.ndarray, pose: np.ndarray,
                             current: _Current | None = None, K: np.ndarray | None = None) -> None:
        c = self.config
        ref = self.reference
        translation, rotation_deg = relative_motion(ref.pose, pose)
        if (self.last_overlap < c.new_reference_overlap or translation > c.new_reference_translation *
                ref.median_depth or rotation_deg > c.new_reference_rotation_deg):
            if current is not None and self._come_back(index, pose, current, K):
                return
            if np.count_nonzero(depth) > 0.2 * depth.size:
                pyramid = current.pyramid if current is not None else None
                self.references.append(_Reference(index, pose, grey, depth, pyramid=pyramid))

    def _come_back(self, index: int, pose: np.ndarray, current: _Current, K: np.ndarray) -> bool:
        """Switch the reference to the nearest place the camera has come back to, when the frame overlaps it well;
        its pose is re-anchored so that this frame keeps `pose` (no jump)."""
        c = self.config
        place = self._nearest_place(index, pose)
        if place is None:
            return False
        candidate = place.reference(place.pose)
        reference = candidate.pyramid(K, c.pyramid_levels, self.settings.backend)
        T_init = np.linalg.inv(pose) @ place.pose
        result = align(reference, current.pyramid, T_init, self.settings)
        if not result.ok or result.overlap < c.reuse_overlap:
            seed = pnp_seed(candidate.keypoints(K, c.pyramid_levels), current.keypoints(), K)
            if seed is not None:
                result = _best([result, align(reference, current.pyramid, seed, self.settings)])
        if (not result.ok or result.overlap < c.reuse_overlap
                or result.photometric_rms > min(c.max_photometric_residual,
                                                c.seed_residual_ratio * self.typical_residual)):
            return False
        moved, turned = relative_motion(place.pose, pose @ result.T)
        if moved > c.max_jump * place.median_depth or turned > 4 * c.reuse_rotation_deg:
            return False  # the place is not where the odometry has it: leave it to loop closure
        candidate.pose = place.pose = pose @ result.T
        self.references.append(candidate)
        self.last_overlap = result.overlap
        log.debug("frame %d: tracking against keyframe %d again", index, place.index)
        return True

    def _nearest_place(self, index: int, pose: np.ndarray) -> _Place | None:
        """The place at least `reuse_min_age` frames old nearest the camera within the reuse distance and angle,
        other than the current reference."""
        c = self.config
        best, best_score = None, np.inf
        current = self.reference.index if self.reference is not None else None
        for place in self.places:
            if index - place.index < c.reuse_min_age or place.index == current:
                continue
            moved, turned = relative_motion(place.pose, pose)
            if moved > c.reuse_distance * place.median_depth or turned > c.reuse_rotation_deg:
                continue
            score = moved / (c.reuse_distance * place.median_depth) + turned / c.reuse_rotation_deg
            if score < best_score:
                best, best_score = place, score
        return best

    # ------------------------------------------------------------------------------------------ snapshot/restore
    def state_dict(self) -> dict[str, Any]:
        return {"references": [r.to_dict() for r in self.references], "last_pose": self.last_pose,
                "previous_pose": self.previous_pose, "lost": self.lost, "typical_residual": self.typical_residual,
                "estimated_intrinsics": None if self.estimated_intrinsics is None else
                self.estimated_intrinsics.to_dict(), "calibrating": self.calibrating,
                "calibration": [[i, _u8(g), d.astype(np.float16)] for i, g, d in self._calibration],
                "places": [p.to_dict() for p in self.places]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.references = deque((_Reference.from_dict(r) for r in state["references"]),
                                maxlen=self.config.reference_ring)
        self.last_pose = None if state["last_pose"] is None else np.asarray(state["last_pose"], np.float64)
        self.previous_pose = None if state["previous_pose"] is None else np.asarray(state["previous_pose"],
                                                                                    np.float64)
        self.lost = bool(state["lost"])
        self.typical_residual = float(state.get("typical_residual", self.config.max_photometric_residual))
        if state.get("estimated_intrinsics"):
            self.estimated_intrinsics = Intrinsics.from_dict(state["estimated_intrinsics"])
        self.calibrating = bool(state.get("calibrating", False))
        self.places = deque((_Place.from_dict(p) for p in state.get("places", [])),
                            maxlen=max(1, self.config.reuse_keyframes))
        self._calibration = [(int(i), np.asarray(g, np.uint8).astype(np.float32) / 255.0, np.asarray(d, np.float32))
                             for i, g, d in state.get("calibration", [])]
