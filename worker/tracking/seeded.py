"""Seeded tracking: device poses seed and constrain tracking, they never replace it (`input.pose_mode: seeded`).

A phone's or a dataset's poses are not the colour camera's truth: ARKit/ARCore drift and jump when they relocalise,
a depth camera's trajectory follows the depth camera. With them, the session's own odometry still tracks every frame
(RGB-D odometry with depth, visual odometry without), and the device only helps:

- its relative motion since the previous frame is the odometry's initial guess where the constant-velocity guess
  misses it (a sudden motion), unless it disagrees with the recent tracked motion by more than a jump;
- the tracked motion is compared with the device's (worker.tracking.device_check): a disagreement beyond
  `jump_translation` / `jump_rotation_deg` (grown by `jump_relative` of the tracked motion's own size: frames far
  apart carry an odometry error in proportion) is a device jump: a `device_pose_jump` event, the device world is
  re-anchored so that the jump does not reach the priors (`correction`), and the next keyframe gets no prior;
- with depth, a disagreement is first put to the images (`arbitrate_jumps`): the frame is aligned again from the
  device's motion, and where that alignment fits clearly better, the odometry slipped (an `odometry_slip` event;
  the device's side is kept) rather than the device jumped;
- each keyframe's device pose goes to the pose graph as an absolute prior with the stated uncertainty
  (`device_poses.prior_translation`, `prior_rotation_deg`), inflated where the device and the tracked poses
  disagree by more (`prior_inflation`): loop closures weigh it against the odometry;
- monocular: the odometry's scale drifts (`drift_correction`). By default (`reanchor`) it is measured again at
  each keyframe over the last ones and the world re-anchored there: the trajectory keeps the device's scale, while
  new keyframes and the map built before them differ in scale. With `settle` the initialisation's two-view scale
  is measured again only until a full window of keyframes measured it, then kept: the map stays at one scale, and
  the trajectory drifts from the device's as the odometry does until a loop closure weighs the priors
  (`settle_tolerance` re-anchors once where the drift passes a share). With `pose_graph` the scale settles likewise,
  the priors leave each node's scale free, and the loop-closing stage solves the graph every few priors
  (`drift_corrected`), moving past keyframes and their part of the map. A new map the odometry makes after a loss
  takes the device's scale again (`_align_monocular`).

The output lives in the device's world: the odometry's world is aligned to the device pose of its first frame
(rigid with depth; for monocular visual odometry, also scaled by the device's baseline over its initialisation).
While the odometry has no world yet (monocular initialisation) or is lost, poses follow the device's motion from
the last output (never a jump, never a held pose while the device still moves); where visual odometry follows a
turn by its rotation alone (the position held or predicted), the frame keeps that rotation and takes its position
from the device's motion, and the difference is no device jump. With depth, a frame the odometry
loses (a fast or sparse motion its own guess misses) is aligned again from the device's pose, and where that fails
too the odometry restarts at the device's pose (`relocalized`, method `device_pose`, after the `tracking_lost`):
tracking and keyframes go on instead of waiting for the view of the last reference to come back
(`device_poses.resume_when_lost`).
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.events import DevicePoseJump, EngineEvent, Initialized, MapsMerged, OdometrySlip, Relocalized
from worker.geometry import Intrinsics, fit_similarity
from worker.loop.pose_graph import EdgeSigmas, PosePrior
from worker.tracking.base import TrackingResult
from worker.tracking.dense_alignment import fits_clearly_better
from worker.tracking.device_check import (
    MotionDisagreement,
    checked_device_pose,
    disagreement,
    motion_size,
    relative,
)
from worker.tracking.device_clock import DeviceClock, clock_state, load_clock_state, retimed
from worker.tracking.keyframe_scale import local_scales, scale_spread, scaled_moves
from worker.tracking.seeded_config import DevicePoseConfig

log = logging.getLogger(__name__)

# Frames kept (output and device pose) while a monocular odometry initialises, to anchor its world at.
MAX_WAITING_FRAMES = 300
# Log-scale standard deviation of a device prior: device poses are metric.
PRIOR_LOG_SCALE_SIGMA = 1e-3
# ... where the pose graph corrects a monocular odometry's drift: a device pose places its keyframe but says nothing
# of the scale its part of the map was built at (the odometry's edges carry that), so the node's scale is free.
DRIFT_PRIOR_LOG_SCALE_SIGMA = 1.0


def _scaled(pose: np.ndarray, scale: float) -> np.ndarray:
    out = np.array(pose, np.float64)
    out[:3, 3] *= scale
    return out


# Frames marked beyond the odometry's archive bound: its window's keyframes, not archived yet.
MARKS_BEYOND_ARCHIVE = 64
# A keyframe whose device pose lies this many times the median distance from the fitted one is left out of the fit.
MARK_OUTLIER_FACTOR = 3.0


def _fit_robustly(own: list[np.ndarray], device: list[np.ndarray]) -> np.ndarray | None:
    """The similarity laying `own` poses on `device` poses (`fit_similarity`), fitted once more without the poses
    it leaves far off (a device jump, a stretch the device lost)."""
    similarity = fit_similarity(own, device)
    if similarity is None:
        return None
    off = np.array([np.linalg.norm((similarity @ o)[:3, 3] - d[:3, 3]) for o, d in zip(own, device)])
    kept = off <= MARK_OUTLIER_FACTOR * max(float(np.median(off)), 1e-9)
    if kept.all() or kept.sum() < 3:
        return similarity
    return fit_similarity([o for o, k in zip(own, kept) if k], [d for d, k in zip(device, kept) if k])


class SeededTracking:
    """A pose source (RGB-D or visual odometry) seeded and checked by the frames' device poses (module docstring).

    odometry: the inner source, whose `track` takes a `motion_guess`; monocular: its units are not metric (the
    scale is found from the device's baseline); publish_prior: where keyframe priors go (the loop-closing stage).
    """

    name = "seeded"

    def __init__(self, odometry, config: DevicePoseConfig | None = None, monocular: bool = False,
                 publish_prior: Callable[[PosePrior], None] | None = None) -> None:
        self.odometry = odometry
        self.config = config or DevicePoseConfig()
        self.monocular = monocular
        self.publish_prior = publish_prior
        self.alignment: np.ndarray | None = None  # session world <- odometry world (rigid), once it has one
        self.scale = 1.0  # session units per odometry unit
        self.measured_scale = 1.0  # ... as the device last measured it (the same until the scale settles)
        self.correction = np.eye(4)  # session world <- device world: absorbs the device's jumps
        self.last_device: np.ndarray | None = None  # device pose of the last frame (device world)
        self.last_index: int | None = None
        self.last_pose: np.ndarray | None = None  # output of the last frame
        self.previous_pose: np.ndarray | None = None  # output of the frame before
        self.last_tracked = False  # whether the last output came from the odometry
        # (output, device pose) of the frames while the odometry has no world (monocular initialisation, also after
        # it lost its map and starts a new one): its world is anchored at one of them when it is made
        self.waiting: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.skip_next_prior = False
        # (device position, odometry position) of the last keyframes since a jump: the monocular scale's measure
        self.scale_marks: list[tuple[np.ndarray, np.ndarray]] = []
        self.last_prior: tuple[np.ndarray, np.ndarray] | None = None  # (device, tracked) pose of the last prior
        # settle, pose_graph: the scale was measured over a full `scale_keyframes` window and is kept from then on
        self.scale_settled = False
        self.lost_since: float | None = None  # timestamp of the first frame of the odometry's current loss
        self.jumps = 0
        self.slips = 0  # disagreements the images laid on the odometry
        self.priors_sent = 0
        self.priors_dropped = 0
        self.device_clock: DeviceClock | None = None  # re-times the device poses first, when set
        # (output, device pose in the session's world) of the frames that became the odometry's keyframes, for its
        # final adjustment's placing in the device's world (memory only, as the odometry's keyframe archive)
        self.keyframe_marks: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.placed: set[int] | None = None  # the keyframes `keyframe_corrections` placed, once it ran
        self.placed_scales: tuple[float, float, float] | None = None  # ... and the spread of their local scales

    # -- what the engine reads from a pose source ---------------------------------------------------------------
    @property
    def estimated_intrinsics(self) -> Intrinsics | None:
        return getattr(self.odometry, "estimated_intrinsics", None)

    @property
    def final_adjustment(self):
        """The odometry's final bundle adjustment, once `keyframe_corrections` ran it (None before, or without);
        monocular, with the poses of the keyframes it placed in the device's world only (none where it gave up)."""
        result = getattr(self.odometry, "final_adjustment", None)
        if result is None or not self.monocular or self.placed is None:
            return result
        return replace(result, poses={k: p for k, p in result.poses.items() if k in self.placed},
                       local_scales=self.placed_scales)

    @property
    def calibrating(self) -> bool:
        return bool(getattr(self.odometry, "calibrating", False))

    # -- tracking ------------------------------------------------------------------------------------------------
    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        frame = retimed(self.device_clock, frame, intrinsics)
        if frame.pose is None:
            return self._track_without_device(frame, intrinsics)
        device = checked_device_pose(frame.pose, frame.index)
        device_motion = None if self.last_device is None else relative(self.last_device, device)
        if not self.monocular and frame.depth is None:  # nothing to align: follow the device for this frame
            result = TrackingResult(np.eye(4), tracked=False, keyframe_hint=False)
        else:
            before = self.odometry.checkpoint() if self._can_arbitrate(device_motion) else None
            result = self.odometry.track(frame, intrinsics, motion_guess=self._guess(device_motion))
            if before is not None and result.tracked and self._jumped(device_motion, result.pose):
                result = self._arbitrate(frame, intrinsics, device_motion, result, before)
            if not result.tracked and self._can_resume(device_motion):
                result = self._resume(frame, intrinsics, device_motion, result)
            if result.tracked:
                self.lost_since = None
        # A monocular join (maps_merged) measures in odometry units; the device's poses place this world instead.
        events = [e for e in result.events if not isinstance(e, (Initialized, MapsMerged))]
        initialized = [e for e in result.events if isinstance(e, Initialized)]
        if initialized and self.monocular:
            self._align_monocular(initialized[-1], device, result.pose)
        elif self.alignment is None and result.tracked and not self.monocular:
            self.alignment = self.correction @ device @ np.linalg.inv(result.pose)
        events += [self._in_session(e) for e in initialized]
        from_odometry = self.alignment is not None and result.tracked and not self._waiting_for_world(initialized)
        device_step = (None if self.last_pose is None or device_motion is None
                       else self.last_pose @ self._in_output_units(device_motion))
        if from_odometry:
            pose = self.to_session(result.pose)
            if not result.translation_measured and device_step is not None:
                pose[:3, 3] = device_step[:3, 3]  # a turn the odometry followed by rotation alone: the device moved
        elif device_step is not None:
            pose = device_step
        else:
            pose = self.correction @ device
        if from_odometry and self.last_tracked and device_motion is not None and result.translation_measured:
            events += self._check_jump(frame.index, device, device_motion, relative(self.last_pose, pose))
        if self.monocular and (self.alignment is None or self._waiting_for_world(initialized)):
            self.waiting[frame.index] = (pose.copy(), device)
            while len(self.waiting) > MAX_WAITING_FRAMES:
                del self.waiting[next(iter(self.waiting))]
        if from_odometry and self.monocular:
            self._mark_keyframe(frame.index, pose, self.correction @ device)
        self.previous_pose, self.last_pose = self.last_pose, pose
        self.last_device, self.last_index, self.last_tracked = device, frame.index, from_odometry
        depth = None if result.depth is None or not from_odometry else result.depth * np.float32(self.scale)
        return TrackingResult(pose.copy(), tracked=result.tracked, depth=depth, events=events,
                              keyframe_hint=result.keyframe_hint if from_odometry else False,
                              quality=result.quality if from_odometry else None,
                              anchor=self._anchor_in_session(result) if from_odometry else None)

    def _track_without_device(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        """A frame without a device pose (the device not ready yet, a gap in its log): the odometry tracks it alone
        once the two worlds are aligned; before that, or without depth to align, the last pose is held (lost). The
        next frame's device motion spans the gap, so it neither seeds nor checks for a jump."""
        held = np.eye(4) if self.last_pose is None else self.last_pose
        self.last_device = None
        if self.alignment is None or (not self.monocular and frame.depth is None):
            self.last_tracked = False
            return TrackingResult(held.copy(), tracked=False, keyframe_hint=False)
        result = self.odometry.track(frame, intrinsics)
        events = [e for e in result.events if not isinstance(e, Initialized)]
        self.last_tracked = result.tracked
        if not result.tracked:
            return TrackingResult(held.copy(), tracked=False, keyframe_hint=False, events=events)
        pose = self.to_session(result.pose)
        self.previous_pose, self.last_pose, self.last_index = self.last_pose, pose, frame.index
        depth = None if result.depth is None else result.depth * np.float32(self.scale)
        return TrackingResult(pose.copy(), depth=depth, events=events, keyframe_hint=result.keyframe_hint,
                              quality=result.quality, anchor=self._anchor_in_session(result))

    def _mark_keyframe(self, index: int, pose: np.ndarray, device: np.ndarray) -> None:
        """Remember the output and device pose of a frame the odometry made a keyframe of (bounded as its archive)."""
        made = getattr(self.odometry, "is_keyframe", None)
        if made is None or not made(index):
            return
        self.keyframe_marks[index] = (pose.copy(), np.array(device, np.float64))
        bound = getattr(self.odometry.config, "final_adjustment_keyframes", 0) + MARKS_BEYOND_ARCHIVE
        while len(self.keyframe_marks) > bound:
            self.keyframe_marks.popitem(last=False)

    def keyframe_corrections(self) -> dict[int, np.ndarray]:
        """Monocular: the odometry's final bundle adjustment placed in the device's world. Its adjusted keyframes
        have one scale and no drift; the one similarity that best lays them on their device poses (rotations
        averaged, then scale and position by least squares, keyframes off by more than `MARK_OUTLIER_FACTOR` times
        the median fitted again without them) puts them in the session's world and units. Returns, by frame index,
        each keyframe's move from the pose its frame was given to that placed pose, a similarity carrying the local
        scale (worker.tracking.keyframe_scale); {} where the odometry did not adjust, or fewer than three keyframes
        have device poses."""
        adjust = getattr(self.odometry, "adjusted_keyframes", None)
        if not self.monocular or adjust is None:
            return {}
        adjusted = {k: poses[1] for k, poses in adjust().items() if k in self.keyframe_marks}
        similarity = _fit_robustly([adjusted[k] for k in adjusted],
                                   [self.keyframe_marks[k][1] for k in adjusted]) if len(adjusted) >= 3 else None
        placed = {}
        for k, pose in adjusted.items() if similarity is not None else ():
            placed[k] = similarity @ pose
            placed[k][:3, :3] /= np.cbrt(np.linalg.det(placed[k][:3, :3]))
        given = {k: self.keyframe_marks[k][0] for k in placed}
        scales = local_scales(given, placed)
        self.placed, self.placed_scales = set(placed), scale_spread(scales)
        return scaled_moves(given, placed, scales)

    def _can_resume(self, device_motion: np.ndarray | None) -> bool:
        """Whether a frame the RGB-D odometry lost can be tracked again from the device's pose."""
        return (self.config.resume_when_lost and not self.monocular and device_motion is not None
                and self.alignment is not None and self.last_pose is not None
                and hasattr(self.odometry, "resume_from"))

    def _resume(self, frame: Frame, intrinsics: Intrinsics | None, device_motion: np.ndarray,
                lost: TrackingResult) -> TrackingResult:
        """The lost frame aligned again from where the device says the camera is, or the odometry restarted
        there (module docstring). Its `tracking_lost` is reported only with a restart: a frame the device's
        pose let the odometry align was tracked."""
        if self.lost_since is None:
            self.lost_since = frame.timestamp
        restart = frame.timestamp - self.lost_since >= self.config.resume_after_s
        result = self.odometry.resume_from(frame, intrinsics, self.to_odometry(self.last_pose @ device_motion),
                                           min_sharpness_ratio=self.config.resume_sharpness, restart=restart)
        restarted = any(isinstance(e, Relocalized) for e in result.events)
        if result.tracked and not restarted:
            return result
        return TrackingResult(result.pose, tracked=result.tracked, depth=result.depth,
                              events=lost.events + result.events,
                              keyframe_hint=result.keyframe_hint, quality=result.quality)

    def _can_arbitrate(self, device_motion: np.ndarray | None) -> bool:
        """Whether a disagreement on this frame can be put to the images (depth, an aligned world, the last frame
        tracked, an odometry that can track a frame again)."""
        return (self.config.arbitrate_jumps and not self.monocular and device_motion is not None
                and self.alignment is not None and self.last_tracked and self.last_pose is not None
                and hasattr(self.odometry, "checkpoint"))

    def _jumped(self, device_motion: np.ndarray, odometry_pose: np.ndarray) -> bool:
        """Whether the device's motion into the frame disagrees beyond a jump with the odometry's pose of it."""
        return self._jump_gap(device_motion, relative(self.last_pose, self.to_session(odometry_pose))) is not None

    def _jump_gap(self, device_motion: np.ndarray, tracked_motion: np.ndarray) -> MotionDisagreement | None:
        """The two motions' disagreement where it exceeds the jump thresholds (grown with the motion), else None."""
        c = self.config
        gap = disagreement(device_motion, tracked_motion)
        size = motion_size(tracked_motion)
        beyond = gap.exceeds(c.jump_translation + c.jump_relative * size.translation,
                             c.jump_rotation_deg + c.jump_relative * size.rotation_deg)
        return gap if beyond else None

    def _arbitrate(self, frame: Frame, intrinsics: Intrinsics | None, device_motion: np.ndarray,
                   result: TrackingResult, before) -> TrackingResult:
        """The device and the odometry disagree: the frame is tracked again from the device's motion. Where that
        alignment fits the images clearly better and agrees with the device, the odometry slipped: the new result
        replaces it (`odometry_slip`). Otherwise the odometry's result stands (the device jumped)."""
        odometry_fit = self.odometry.last_alignment
        after = self.odometry.checkpoint()
        self.odometry.restore(before)
        again = self.odometry.track(frame, intrinsics, motion_guess=_scaled(device_motion, 1.0 / self.scale))
        device_fit = self.odometry.last_alignment
        if (again.tracked and odometry_fit is not None and device_fit is not odometry_fit
                and fits_clearly_better(device_fit, odometry_fit, self.config.slip_fit_ratio)
                and not self._jumped(device_motion, again.pose)):
            self.slips += 1
            log.info("frame %d: the odometry slipped (intensity residual %.4f -> %.4f from the device's motion): "
                     "re-tracked from the device", frame.index, odometry_fit.photometric_rms,
                     device_fit.photometric_rms)
            event = OdometrySlip(
                frame=int(frame.index),
                photometric_rms=[round(odometry_fit.photometric_rms, 5), round(device_fit.photometric_rms, 5)],
                geometric_rms=[round(odometry_fit.geometric_rms, 5), round(device_fit.geometric_rms, 5)],
                action="re-tracked from the device's motion")
            return TrackingResult(again.pose, tracked=True, depth=again.depth, events=[*again.events, event],
                                  keyframe_hint=again.keyframe_hint, quality=again.quality)
        self.odometry.restore(after)
        return result

    def _waiting_for_world(self, initialized: list[Initialized]) -> bool:
        """A monocular odometry still initialising (its poses are placeholders)."""
        return self.monocular and not initialized and getattr(self.odometry, "status", "tracking") == "initializing"

    def _guess(self, device_motion: np.ndarray | None) -> np.ndarray | None:
        """The device's motion in odometry units as the initial guess where it tells the odometry something: when
        the constant-velocity guess misses it by more than `seed_translation` / `seed_rotation_deg` (a sudden
        motion), but not by more than a jump (a device jump must not mislead the alignment). Otherwise None: the
        odometry's own guess (the two agree; a device's small per-frame bias would only leak into a partly
        converged alignment)."""
        if device_motion is None or self.alignment is None or not self.last_tracked:
            return None
        if self.previous_pose is None:
            return _scaled(device_motion, 1.0 / self.measured_scale)
        c = self.config
        recent = disagreement(self._in_output_units(device_motion), relative(self.previous_pose, self.last_pose))
        if recent.exceeds(c.jump_translation, c.jump_rotation_deg) or not recent.exceeds(c.seed_translation,
                                                                                        c.seed_rotation_deg):
            return None
        return _scaled(device_motion, 1.0 / self.measured_scale)

    def _check_jump(self, index: int, device: np.ndarray, device_motion: np.ndarray, tracked_motion: np.ndarray
                    ) -> list[EngineEvent]:
        """A `device_pose_jump` event when the device's motion disagrees with the tracked one; the device world
        is then re-anchored so that this frame's device pose continues the tracked motion."""
        gap = self._jump_gap(self._in_output_units(device_motion), tracked_motion)
        if gap is None:
            return []
        self.correction = (self.correction @ self.last_device @ _scaled(tracked_motion, self._drift())
                           @ np.linalg.inv(device))
        self.skip_next_prior = True
        self.scale_marks = []  # distances across the jump measure nothing
        self.scale_settled = False  # ... and the scale kept before it may be what made the jump: measured again
        self.jumps += 1
        log.warning("frame %d: the device pose jumped (%.3f, %.1f deg from the tracked motion): re-anchored, its "
                    "keyframe prior dropped", index, gap.translation, gap.rotation_deg)
        return [DevicePoseJump(frame=int(index), translation=round(gap.translation, 4),
                               rotation_deg=round(gap.rotation_deg, 3), action="prior dropped, device re-anchored")]

    def _align_monocular(self, event: Initialized, device: np.ndarray, odometry_pose: np.ndarray) -> None:
        """Visual odometry made its map: the first one's world is the reference frame's camera (identity pose) at
        an arbitrary scale, aligned to the reference frame's output so far and scaled by the device's baseline
        since it. A new map after a loss may continue the odometry's old world, its first frames holding a
        placeholder pose: it is scaled by the median of the device's over the odometry's steps between the frames
        it re-estimated and aligned at the last of them. Either way the scale's window starts again (a new map's
        scale is a new two-view guess)."""
        frames = {int(i): np.asarray(p, np.float64) for i, p in event.frames or []}
        reference = next((i for i, p in frames.items() if np.allclose(p, np.eye(4), atol=1e-9)), None)
        shared = sorted(i for i in frames if i in self.waiting)
        if reference in self.waiting or not shared:
            if reference in self.waiting:
                anchor, anchor_device = self.waiting[reference]
            elif self.last_pose is not None and self.last_device is not None:
                anchor, anchor_device = self.last_pose, self.last_device
            else:
                anchor, anchor_device = self.correction @ device, device
            odometry_anchor = frames.get(reference, np.eye(4))
            baseline = float(np.linalg.norm(relative(anchor_device, device)[:3, 3]))
            travelled = float(np.linalg.norm(relative(odometry_anchor, odometry_pose)[:3, 3]))
            self.scale = baseline / travelled if baseline > 1e-6 and travelled > 1e-9 else 1.0
        else:
            reference = shared[-1]
            anchor, odometry_anchor = self.waiting[reference][0], frames[reference]
            devices = [self.waiting[i][1] for i in shared] + [device]
            odometries = [frames[i] for i in shared] + [odometry_pose]
            ratios = [float(np.linalg.norm(relative(d0, d1)[:3, 3]) / np.linalg.norm(relative(o0, o1)[:3, 3]))
                      for d0, d1, o0, o1 in zip(devices, devices[1:], odometries, odometries[1:])
                      if np.linalg.norm(relative(o0, o1)[:3, 3]) > 1e-9]
            ratios = [r for r in ratios if r > 1e-6]
            self.scale = float(np.median(ratios)) if ratios else self.scale
        self.measured_scale = self.scale
        self.alignment = anchor @ np.linalg.inv(_scaled(odometry_anchor, self.scale))
        self.waiting = {}
        self.scale_marks, self.scale_settled = [], False
        log.info("seeded visual odometry: world aligned at frame %s, %.4f units per odometry unit", reference,
                 self.scale)

    def _in_session(self, event: Initialized) -> Initialized:
        """An `initialized` event with its re-estimated frames in the session's world."""
        if not event.frames or self.alignment is None:
            return event
        return replace(event, frames=[[int(i), self.to_session(np.asarray(p, np.float64)).tolist()]
                                      for i, p in event.frames])

    def _corrects_in_graph(self) -> bool:
        """Whether the pose graph, not a re-anchored world, corrects the monocular odometry's scale drift."""
        return self.monocular and self.config.drift_correction == "pose_graph"

    def _drift(self) -> float:
        """The odometry's scale as last measured over the one its world keeps (1 until the scale settles)."""
        return self.measured_scale / self.scale

    def _in_output_units(self, device_motion: np.ndarray) -> np.ndarray:
        """A device motion in the units of the output's world (the odometry's once the scale settled)."""
        return _scaled(device_motion, 1.0 / self._drift())

    def _anchor_in_session(self, result: TrackingResult) -> tuple[int, np.ndarray] | None:
        """The odometry's anchor (an earlier keyframe and the pose measured against it) in the session's units; none
        where the position was not measured."""
        if result.anchor is None or not result.translation_measured:
            return None
        keyframe, relative = result.anchor
        return keyframe, _scaled(relative, self.scale)

    def to_session(self, odometry_pose: np.ndarray) -> np.ndarray:
        """An odometry pose in the session's (device) world."""
        return self.alignment @ _scaled(odometry_pose, self.scale)

    def to_odometry(self, session_pose: np.ndarray) -> np.ndarray:
        """A session pose in the odometry's world and units."""
        return _scaled(np.linalg.inv(self.alignment) @ np.asarray(session_pose, np.float64), 1.0 / self.scale)

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The odometry may keep the keyframe as a place; the device's pose of it goes to the pose graph as a prior
        (none right after a jump)."""
        frame = retimed(self.device_clock, frame, None)
        if self.alignment is not None:
            self.odometry.keyframe_added(frame, self.to_odometry(pose))
            if self.monocular and frame.pose is not None and not self.skip_next_prior:
                self._measure_scale(self.correction @ checked_device_pose(frame.pose, frame.index), pose)
        if self.publish_prior is None or frame.pose is None:
            return
        if self.skip_next_prior:
            self.skip_next_prior = False
            self.priors_dropped += 1
            return
        device = self.correction @ checked_device_pose(frame.pose, frame.index)
        sigmas = self._drift_prior_sigmas(device, pose) if self._corrects_in_graph() else self._prior_sigmas(
            device, pose)
        self.publish_prior(PosePrior(int(frame.index), device, sigmas))
        self.priors_sent += 1

    def _measure_scale(self, device: np.ndarray, pose: np.ndarray) -> None:
        """Monocular odometry drifts in scale: at a keyframe (device pose `device`, output `pose`), the scale is
        the device's over the odometry's distances between the last `scale_keyframes` keyframes, and the world is
        re-anchored at this keyframe with it (its output stays where it is; the motion after it takes the new
        scale)."""
        c = self.config
        if c.scale_keyframes <= 0:
            return
        odometry = self.to_odometry(pose)
        marks = [*self.scale_marks, (device[:3, 3].copy(), odometry[:3, 3].copy())]
        self.scale_marks = marks[-(c.scale_keyframes + 1):]
        if len(self.scale_marks) < 3:
            return
        devices = np.stack([d for d, _ in self.scale_marks])
        odometries = np.stack([o for _, o in self.scale_marks])
        device_steps = np.linalg.norm(np.diff(devices, axis=0), axis=1)
        odometry_steps = np.linalg.norm(np.diff(odometries, axis=0), axis=1)
        measured = device_steps >= c.scale_min_baseline
        if measured.sum() < 2 or odometry_steps[measured].sum() <= 1e-9:
            return
        self.measured_scale = float(device_steps[measured].sum() / odometry_steps[measured].sum())
        if self.scale_settled and not self._settled_scale_off(c):  # the world keeps its scale (one map scale)
            return
        self.scale = self.measured_scale
        self.alignment = pose @ np.linalg.inv(_scaled(odometry, self.scale))
        # settle, pose_graph: the initialisation's two-view scale is re-measured over the first full window of
        # keyframes, then kept (in the graph, whose gauge holds the first keyframe's scale, a first scale far off
        # would also bend the map there)
        self.scale_settled = c.drift_correction != "reanchor" and len(self.scale_marks) > c.scale_keyframes

    def _settled_scale_off(self, c: DevicePoseConfig) -> bool:
        """settle: whether the odometry's scale has drifted from the kept one by more than `settle_tolerance`
        (the world is then re-anchored once at the measured scale, and kept at it again)."""
        tolerance = c.settle_tolerance if c.drift_correction == "settle" else 0.0
        return tolerance > 0 and abs(math.log(self.measured_scale / self.scale)) > math.log1p(tolerance)

    def _prior_sigmas(self, device: np.ndarray, tracked: np.ndarray) -> EdgeSigmas:
        """The stated uncertainty of a device pose, inflated to `prior_inflation` times its disagreement with the
        tracked pose: a prior never claims to be surer than what the two trajectories show (drifting device poses
        weigh less and less against the odometry; accurate ones keep the stated weight and correct its drift)."""
        c = self.config
        gap = disagreement(device, tracked)
        return EdgeSigmas(max(math.radians(c.prior_rotation_deg), c.prior_inflation * math.radians(gap.rotation_deg)),
                          max(c.prior_translation, c.prior_inflation * gap.translation), PRIOR_LOG_SCALE_SIGMA)

    def _drift_prior_sigmas(self, device: np.ndarray, tracked: np.ndarray) -> EdgeSigmas:
        """A device prior where the pose graph corrects the odometry's drift: the tracked pose is off by the drift
        itself, so the stated uncertainty is inflated by the disagreement of the motions since the last prior
        (the device's against the tracked one at the measured scale), and the node's scale is left free."""
        c = self.config
        last, self.last_prior = self.last_prior, (device.copy(), np.asarray(tracked, np.float64).copy())
        rotation, translation = math.radians(c.prior_rotation_deg), c.prior_translation
        if last is not None:
            gap = disagreement(relative(last[0], device), _scaled(relative(last[1], tracked), self._drift()))
            rotation = max(rotation, c.prior_inflation * math.radians(gap.rotation_deg))
            translation = max(translation, c.prior_inflation * gap.translation)
        return EdgeSigmas(rotation, translation, DRIFT_PRIOR_LOG_SCALE_SIGMA)

    # -- snapshot ------------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"odometry": self.odometry.state_dict(), "alignment": self.alignment, "scale": self.scale,
                "correction": self.correction, "last_device": self.last_device, "last_index": self.last_index,
                "last_pose": self.last_pose, "previous_pose": self.previous_pose, "last_tracked": self.last_tracked,
                "waiting": [[i, p, d] for i, (p, d) in self.waiting.items()], "skip_next_prior": self.skip_next_prior,
                "counts": [self.jumps, self.priors_sent, self.priors_dropped, self.slips],
                "scale_marks": [[d, o] for d, o in self.scale_marks], "lost_since": self.lost_since,
                "measured_scale": self.measured_scale, "scale_settled": self.scale_settled,
                "last_prior": None if self.last_prior is None else list(self.last_prior),
                **clock_state(self.device_clock)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        def matrix(value) -> np.ndarray | None:
            return None if value is None else np.asarray(value, np.float64)

        load_clock_state(self.device_clock, state)
        self.odometry.load_state_dict(state["odometry"])
        self.alignment, self.scale = matrix(state["alignment"]), float(state["scale"])
        self.correction = matrix(state["correction"])
        self.last_device, self.last_index = matrix(state["last_device"]), state["last_index"]
        self.last_pose, self.previous_pose = matrix(state["last_pose"]), matrix(state["previous_pose"])
        self.last_tracked = bool(state["last_tracked"])
        self.waiting = {int(i): (matrix(p), matrix(d)) for i, p, d in state["waiting"]}
        self.skip_next_prior = bool(state["skip_next_prior"])
        self.lost_since = state.get("lost_since")
        counts = [*state["counts"], 0][:4]  # snapshots before odometry slips were counted have three
        self.jumps, self.priors_sent, self.priors_dropped, self.slips = (int(v) for v in counts)
        self.scale_marks = [(np.asarray(d, np.float64), np.asarray(o, np.float64))
                            for d, o in state.get("scale_marks", [])]
        self.measured_scale = float(state.get("measured_scale", self.scale))
        self.scale_settled = bool(state.get("scale_settled", False))
        last_prior = state.get("last_prior")
        self.last_prior = None if last_prior is None else (matrix(last_prior[0]), matrix(last_prior[1]))


def seeded_tracking(config, with_depth: bool, publish_prior: Callable[[PosePrior], None] | None) -> SeededTracking:
    """The seeded source of a session (a SlamConfig): RGB-D odometry with depth, else visual odometry."""
    if with_depth:
        from worker.tracking.rgbd_odometry import RgbdOdometry

        return SeededTracking(RgbdOdometry(config.tracking.rgbd), config.input.device_poses, False, publish_prior)
    from worker.tracking.visual_odometry import VisualOdometry

    return SeededTracking(VisualOdometry(config.tracking.visual), config.input.device_poses, True, publish_prior)
