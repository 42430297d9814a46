"""Monocular visual odometry as a pose source.

Points are followed from frame to frame by sub-pixel optical flow (Lucas-Kanade, forward-backward checked, guided
by the motion model) and re-matched against the last keyframe's image, so that small errors do not add up from frame
to frame. The map starts from a two-view reconstruction of the first tracks with enough parallax; each frame's pose
then comes from the tracks that measure map points (robust refinement from the constant-velocity guess, PnP + RANSAC
when that fails). Keyframes are taken when tracks drop or the baseline grows: they add new corners, triangulate the
candidate tracks that gained enough parallax since the oldest keyframe that saw them, and run a windowed bundle
adjustment in which the oldest keyframes stay fixed, so scale carries over without rescaling. A lost frame first
tries to take up the last tracked frame's tracks (a short loss), then place recognition with the ORB features the
keyframes keep. When the camera comes back, a keyframe VO takes for its own map is not offered to the engine
(`keyframe_hint=False`) if an engine keyframe at least `reuse_min_age` frames old lies near and sees most of the
frame's tracked map points: a place walked through again keeps the keyframes of its first visit.

Poses are camera-to-world rigid 4x4 matrices (a Sim(3) with s = 1); the world is the camera of the frame the map
was initialised from and the scale makes that map's median depth 1.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics

from .base import TrackingResult
from .bundle_adjustment import bundle_adjust, reprojection_chi2
from .features import Features, OrbExtractor
from .local_map import Keyframe, LocalMap
from .optical_flow import detect_corners, predicted_pixels, refine_points, track_points
from .pose_optimization import optimize_pose
from .projection import camera_matrix, invert_pose, rigid, to_camera
from .relocalization import Place, PlaceRecognizer
from .self_calibration import FocalEstimator
from .track_triangulation import triangulate_tracks
from .tracks import Tracks, lookup_sorted
from .two_view import TwoViewMap, two_view_from_matches
from .vo_config import VisualOdometryConfig

STATE_VERSION = 2


class VisualOdometry:
    """PoseSource for RGB-only streams (see the module docstring)."""

    name = "visual_odometry"

    def __init__(self, config: VisualOdometryConfig | None = None) -> None:
        self.config = config or VisualOdometryConfig()
        self.extractor = OrbExtractor(self.config)
        self.recognizer = PlaceRecognizer(self.config)
        self._reset()

    def _reset(self) -> None:
        self.status = "initializing"  # | "tracking" | "lost"
        self.map = LocalMap()
        self.retired: list[Place] = []  # keyframes that left the window, kept for relocalisation
        self.tracks = Tracks.empty()
        self.next_id = 0
        self.previous_gray: np.ndarray | None = None  # the last frame tracked (flow starts from it)
        self.keyframe_gray: np.ndarray | None = None  # the last keyframe's image (tracks are refined against it)
        self.pending: list[tuple[int, np.ndarray, np.ndarray]] = []  # (index, track ids, uv) of waiting frames
        self.pose = np.eye(4)
        self.velocity = np.eye(4)  # camera motion of the last frame (previous^-1 @ current)
        self.frames_since_keyframe = 0
        self.tracked_at_keyframe = 0
        self.lost_since: int | None = None
        self.image_size: tuple[int, int] | None = None
        self.estimated_intrinsics: Intrinsics | None = None
        self.focal = FocalEstimator(self.config)
        # (frame index, pose) of the engine's keyframes, to come back to
        self.engine_keyframes: deque[tuple[int, np.ndarray]] = deque(maxlen=max(1, self.config.reuse_keyframes))

    # ---- PoseSource ------------------------------------------------------------------------------------------
    def track(self, frame: Frame, intrinsics: Intrinsics | None, motion_guess: np.ndarray | None = None
              ) -> TrackingResult:
        """Track the next frame (see the module docstring); bad frames lose tracking, they never raise.
        `motion_guess` (previous^-1 @ current in this odometry's units, e.g. a device's relative motion) replaces
        the constant-velocity guess when given."""
        camera = self._camera(frame, intrinsics)
        gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
        if self.status == "initializing":
            result = self._initialise(frame.index, gray, camera, intrinsics is None)
        elif self.status == "lost":
            result = self._relocalise(frame.index, gray, camera)
        else:
            result = self._track(frame.index, gray, camera, motion_guess)
        if not np.all(np.isfinite(result.pose)):  # never hand out a NaN pose, whatever happened above
            result = self._lose(frame.index, "non-finite pose estimate")
        self.pose = result.pose
        return result

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The engine's keyframes do not change VO's own; they are remembered as places to come back to."""
        if self.config.reuse_keyframes > 0:
            self.engine_keyframes.append((int(frame.index), np.asarray(pose, np.float64).copy()))

    # ---- camera ----------------------------------------------------------------------------------------------
    def _camera(self, frame: Frame, intrinsics: Intrinsics | None) -> Intrinsics:
        size = (frame.width, frame.height)
        if self.image_size is not None and size != self.image_size:
            raise ValueError(f"frame {frame.index} is {size[0]}x{size[1]} but this session's frames are "
                             f"{self.image_size[0]}x{self.image_size[1]}")
        intrinsics = intrinsics or frame.intrinsics
        if intrinsics is not None and (intrinsics.width, intrinsics.height) != size:
            raise ValueError(f"intrinsics are for {intrinsics.width}x{intrinsics.height} but frame {frame.index} "
                             f"is {size[0]}x{size[1]}")
        self.image_size = size
        if intrinsics is not None:
            return intrinsics
        self.estimated_intrinsics = self.focal.intrinsics(*size)
        return self.estimated_intrinsics

    # ---- optical flow ----------------------------------------------------------------------------------------
    def _flow(self, gray: np.ndarray, guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        return track_points(self.previous_gray, gray, self.tracks.uv, guess, window=c.flow_window,
                            levels=c.flow_levels, max_fb_px=c.flow_fb_px)

    def _replenish(self, gray: np.ndarray) -> None:
        """New candidate tracks at corners away from the existing ones, up to `max_tracks`."""
        c = self.config
        corners = detect_corners(gray, self.tracks.uv, c.max_tracks - len(self.tracks),
                                 c.corner_min_distance * max(gray.shape), c.corner_quality)
        ids = np.arange(self.next_id, self.next_id + len(corners), dtype=np.int64)
        self.next_id += len(corners)
        self.tracks = self.tracks.extend(ids, corners)

    # ---- initialisation --------------------------------------------------------------------------------------
    def _initialise(self, index: int, gray: np.ndarray, camera: Intrinsics, uncalibrated: bool) -> TrackingResult:
        """Follow corners until a waiting frame (the reference) and this one make a two-view map; new corners join
        at every frame, and the reference is the oldest waiting frame that still shares enough tracks (the waiting
        frames before it are posed too when the map is made)."""
        c = self.config
        waiting = TrackingResult(np.eye(4), tracked=True, keyframe_hint=False)
        if self.pending:
            uv, ok = self._flow(gray, None)
            self.tracks = Tracks(self.tracks.ids[ok], uv[ok], self.tracks.rows[ok])
        self.previous_gray = gray
        shared = [int(np.isin(self.tracks.ids, ids, assume_unique=True).sum()) for _, ids, _ in self.pending]
        usable = [n for n, count in enumerate(shared) if count >= c.init_min_matches]
        if not usable:  # the view has moved on: wait from this frame
            self._replenish(gray)
            self.pending = [(index, self.tracks.ids.copy(), self.tracks.uv.copy())]
            return waiting
        reference = usable[0]
        _, ref_ids, ref_uv = self.pending[reference]
        at, found = lookup_sorted(ref_ids, self.tracks.ids)
        common = np.flatnonzero(found)
        if uncalibrated and not self.focal.frozen:
            self.focal.observe_matches(ref_uv[at[common]], self.tracks.uv[common], camera)
            camera = self.estimated_intrinsics = self.focal.intrinsics(camera.width, camera.height)
        K = camera_matrix(camera)
        ones = np.ones(len(common))
        attempt = two_view_from_matches(ref_uv[at[common]], self.tracks.uv[common], K, c, ones, ones,
                                        common, common)
        if attempt.map is None:
            self._replenish(gray)
            self.pending = (self.pending + [(index, self.tracks.ids.copy(), self.tracks.uv.copy())]
                            )[-c.init_max_frames:]
            return waiting
        self.focal.freeze()
        self.pending.append((index, self.tracks.ids.copy(), self.tracks.uv.copy()))
        return self._start_map(index, gray, attempt.map, reference, camera, uncalibrated)

    def _start_map(self, index: int, gray: np.ndarray, two: TwoViewMap, reference: int, camera: Intrinsics,
                   uncalibrated: bool) -> TrackingResult:
        """The map of a successful two-view attempt (two.ia, two.ib: rows of the current tracks) between the
        waiting frame `reference` and this one: two keyframes, adjusted and scaled; the other waiting frames are
        posed against it."""
        K = camera_matrix(camera)
        ref_index, ref_ids, ref_uv = self.pending[reference]
        m = self.map = LocalMap()
        rows = m.add_points(two.points, np.zeros((len(two.points), 32), np.uint8))
        self.tracks.rows[two.ib] = rows
        # The reference keyframe keeps the tracks it shares with this frame; its image is gone, so it has no
        # descriptors (it is no place to relocalise from).
        at, found = lookup_sorted(ref_ids, self.tracks.ids)
        ref_features = Features(ref_uv[at[found]], np.zeros((int(found.sum()), 32), np.uint8),
                                np.zeros(int(found.sum()), np.int32))
        kf_a = Keyframe(ref_index, np.eye(4), ref_features, self.tracks.rows[found].copy(),
                        self.tracks.ids[found].copy())
        m.keyframes = [kf_a]
        kf_b = self._new_keyframe(index, two.pose_b, gray)
        self._adjust(K, fixed_count=1)
        self._normalise_scale()
        pose = kf_b.pose
        between, previous = [], np.eye(4)
        for n, (i, ids, uv) in enumerate(self.pending[:-1]):
            fraction = (n - reference) / (len(self.pending) - 1 - reference)
            previous = np.eye(4) if n == reference else self._pose_between(ids, uv, fraction, pose, K)
            between.append([i, previous.tolist()])
        self.pending = []
        self.velocity = invert_pose(previous) @ pose
        self.status = "tracking"
        event = {"type": "initialized", "frame": index, "frames": between, "points": len(m),
                 "parallax_deg": round(two.parallax_deg, 3)}
        if uncalibrated:
            event["intrinsics"] = camera.to_dict()
        return TrackingResult(pose, tracked=True, keyframe_hint=True, depth=self._sparse_depth(kf_b, camera),
                              events=[event])

    def _pose_between(self, ids: np.ndarray, uv: np.ndarray, fraction: float, pose_b: np.ndarray, K: np.ndarray
                      ) -> np.ndarray:
        """Pose of a frame between the two initial views from its tracks of map points (guess: interpolated)."""
        rotvec = cv2.Rodrigues(pose_b[:3, :3])[0].ravel() * fraction
        guess = np.eye(4)
        guess[:3, :3], guess[:3, 3] = cv2.Rodrigues(rotvec)[0], pose_b[:3, 3] * fraction
        order = np.argsort(self.tracks.ids)
        at, found = lookup_sorted(self.tracks.ids[order], ids)
        rows = np.where(found, self.tracks.rows[order][at], -1)
        has = rows >= 0
        if has.sum() < self.config.min_tracked:
            return guess
        pose, inlier = optimize_pose(guess, self.map.positions[rows[has]], uv[has].astype(np.float64),
                                     np.ones(int(has.sum())), K, self.config.chi2_px)
        return pose if inlier.sum() >= self.config.min_tracked and np.all(np.isfinite(pose)) else guess

    # ---- tracking --------------------------------------------------------------------------------------------
    def _track(self, index: int, gray: np.ndarray, camera: Intrinsics, motion_guess: np.ndarray | None = None
               ) -> TrackingResult:
        c = self.config
        K = camera_matrix(camera)
        predicted = rigid(self.pose @ (self.velocity if motion_guess is None else motion_guess))
        mapped_before = int(self.tracks.mapped.sum())
        found = self._follow(gray, predicted, K)
        if found is None:
            return self._lose(index, "too few map points tracked (sudden motion, occlusion or a new view)")
        pose, tracks, inliers = found
        if inliers < max(c.min_tracked, c.min_survival * mapped_before):
            return self._lose(index, f"{inliers} of {mapped_before} tracked points found again (a sudden change)")
        self.tracks, self.previous_gray = tracks, gray
        self.velocity = rigid(invert_pose(self.pose) @ pose)
        self.frames_since_keyframe += 1
        if not self._needs_keyframe(pose, inliers):
            return TrackingResult(pose, tracked=True, keyframe_hint=False)
        kf = self._insert_keyframe(index, pose, gray, K)
        self.velocity = rigid(self.velocity @ invert_pose(pose) @ kf.pose)
        if self._covered(index, kf.pose, K, camera):
            return TrackingResult(kf.pose, tracked=True, keyframe_hint=False)
        return TrackingResult(kf.pose, tracked=True, keyframe_hint=True, depth=self._sparse_depth(kf, camera))

    def _covered(self, index: int, pose: np.ndarray, K: np.ndarray, camera: Intrinsics) -> bool:
        """Whether an engine keyframe at least `reuse_min_age` frames old lies near `pose` and sees at least
        `reuse_overlap` of the frame's tracked map points (in its image, in front of it)."""
        c = self.config
        t = self.tracks
        points = self.map.positions[t.rows[t.mapped]]
        if c.reuse_keyframes <= 0 or len(points) < c.min_tracked:
            return False
        depth = to_camera(points, pose)[:, 2]
        median = float(np.median(depth[depth > 0])) if np.any(depth > 0) else 1.0
        for kf_index, kf_pose in self.engine_keyframes:
            if index - kf_index < c.reuse_min_age:
                continue
            relative = invert_pose(kf_pose) @ pose
            turned = np.degrees(np.linalg.norm(cv2.Rodrigues(relative[:3, :3])[0]))
            if np.linalg.norm(relative[:3, 3]) > c.reuse_distance * median or turned > c.reuse_rotation_deg:
                continue
            seen = to_camera(points, kf_pose)
            z = np.maximum(seen[:, 2], 1e-9)
            u, v = K[0, 0] * seen[:, 0] / z + K[0, 2], K[1, 1] * seen[:, 1] / z + K[1, 2]
            inside = (seen[:, 2] > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
            if inside.mean() >= c.reuse_overlap:
                return True
        return False

    def _follow(self, gray: np.ndarray, predicted: np.ndarray, K: np.ndarray
                ) -> tuple[np.ndarray, Tracks, int] | None:
        """The tracks carried from the last tracked frame into `gray`, less the pose's outliers, the pose and its
        inlier count (None: too few); nothing is changed."""
        t = self.tracks
        guess = predicted_pixels(t.uv, self.map.positions[t.rows[t.mapped]], t.mapped, self.pose, predicted, K)
        uv, ok = self._flow(gray, guess)
        if (ok & t.mapped).sum() < 0.5 * t.mapped.sum():  # a wrong guess can mislead the flow: try none
            uv_plain, ok_plain = self._flow(gray, None)
            if (ok_plain & t.mapped).sum() > (ok & t.mapped).sum():
                uv, ok = uv_plain, ok_plain
        tracks = self._refine(Tracks(t.ids[ok], uv[ok], t.rows[ok]), gray, predicted)
        found = self._pose_from_tracks(tracks, predicted, K)
        if found is None:
            return None
        pose, inlier = found
        keep = np.ones(len(tracks), bool)
        keep[np.flatnonzero(tracks.mapped)[~inlier]] = False
        return pose, tracks.subset(keep), int(inlier.sum())

    def _refine(self, tracks: Tracks, gray: np.ndarray, predicted: np.ndarray) -> Tracks:
        """The tracks that began at or before the last keyframe, matched against that keyframe's image where their
        image scale has not changed much since (the match is a shift, not a zoom; moving forward zooms)."""
        c = self.config
        if self.keyframe_gray is None or not c.flow_refine_px or not self.map.keyframes:
            return tracks
        kf = self.map.keyframes[-1]
        order = np.argsort(kf.track_ids)
        at, found = lookup_sorted(kf.track_ids[order], tracks.ids)
        zoom = np.ones(len(tracks))
        mapped = tracks.mapped
        if mapped.any():
            points = self.map.positions[tracks.rows[mapped]]
            then, now = to_camera(points, kf.pose)[:, 2], to_camera(points, predicted)[:, 2]
            zoom[mapped] = then / np.maximum(now, 1e-9)
            zoom[~mapped] = np.median(zoom[mapped])
        found &= np.abs(zoom - 1.0) <= c.flow_refine_zoom
        uv = tracks.uv.copy()
        uv[found] = refine_points(self.keyframe_gray, gray, kf.features.keypoints[order[at[found]]], uv[found],
                                  window=c.flow_window, max_shift_px=c.flow_refine_px)
        return Tracks(tracks.ids, uv, tracks.rows)

    def _pose_from_tracks(self, tracks: Tracks, guess: np.ndarray, K: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray] | None:
        """Pose from the tracks of map points (robust refinement, PnP + RANSAC when it fails) and the inlier mask
        over those tracks, or None."""
        c = self.config
        mapped = np.flatnonzero(tracks.mapped)
        if len(mapped) < c.min_tracked:
            return None
        points = self.map.positions[tracks.rows[mapped]]
        uv = tracks.uv[mapped].astype(np.float64)
        sigma = np.ones(len(mapped))
        pose, inlier = optimize_pose(guess, points, uv, sigma, K, c.chi2_px)
        if inlier.sum() < max(c.min_tracked, 0.5 * len(mapped)) or not np.all(np.isfinite(pose)):
            ok, rvec, tvec, found = cv2.solvePnPRansac(points, uv, K, None, iterationsCount=100,
                                                       reprojectionError=2.0 * np.sqrt(c.chi2_px),
                                                       confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
            if not ok or found is None or len(found) < c.min_tracked:
                return None
            w2c = np.eye(4)
            w2c[:3, :3], w2c[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            pose, inlier = optimize_pose(invert_pose(w2c), points, uv, sigma, K, c.chi2_px)
            if inlier.sum() < c.min_tracked or not np.all(np.isfinite(pose)):
                return None
        return pose, inlier

    def _median_depth(self, kf: Keyframe) -> float:
        rows = kf.point_ids[kf.point_ids >= 0]
        if len(rows) == 0:
            return 1.0
        return float(np.median(to_camera(self.map.positions[rows], kf.pose)[:, 2]))

    def _needs_keyframe(self, pose: np.ndarray, tracked: int) -> bool:
        c = self.config
        if self.frames_since_keyframe < c.keyframe_min_gap:
            return False
        last = self.map.keyframes[-1]
        baseline = np.linalg.norm(pose[:3, 3] - last.pose[:3, 3]) / max(self._median_depth(last), 1e-6)
        weak = tracked < c.keyframe_tracked_ratio * self.tracked_at_keyframe
        stale = self.frames_since_keyframe >= c.keyframe_max_gap and baseline > 0.2 * c.keyframe_baseline
        return weak or stale or baseline > c.keyframe_baseline

    # ---- keyframes and the map -------------------------------------------------------------------------------
    def _new_keyframe(self, index: int, pose: np.ndarray, gray: np.ndarray) -> Keyframe:
        """A keyframe of every track (after new corners are added), appended to the map."""
        self._replenish(gray)
        t = self.tracks
        features = Features(t.uv.copy(), np.zeros((len(t), 32), np.uint8), np.zeros(len(t), np.int32))
        kf = Keyframe(index, pose.copy(), features, t.rows.copy(), t.ids.copy(), self.extractor.extract(gray))
        self.map.keyframes.append(kf)
        self.keyframe_gray = gray
        self.frames_since_keyframe = 0
        return kf

    def _insert_keyframe(self, index: int, pose: np.ndarray, gray: np.ndarray, K: np.ndarray) -> Keyframe:
        kf = self._new_keyframe(index, pose, gray)
        self._triangulate(K)
        c = self.config
        gone = self.map.slide(c.window + c.fixed_keyframes)
        self._retire(gone)
        self._remap(self.map.forget_unobserved())
        if len(self.map.keyframes) >= 3:
            self._adjust(K, fixed_count=max(c.fixed_keyframes, len(self.map.keyframes) - c.window))
        self.tracked_at_keyframe = int(self.tracks.mapped.sum())
        return kf

    def _triangulate(self, K: np.ndarray) -> None:
        """Map points from the candidate tracks of the newest keyframe (see `triangulate_tracks`)."""
        m, t = self.map, self.tracks
        candidate = t.rows < 0
        new = triangulate_tracks(m.keyframes, t.ids[candidate], t.uv[candidate], K, self.config.chi2_px,
                                 self.config.min_parallax_deg)
        rows = m.add_points(new.points, np.zeros((len(new.points), 32), np.uint8))
        for keyframe in m.keyframes:
            at, found = lookup_sorted(new.ids, keyframe.track_ids)
            keyframe.point_ids[found] = rows[at[found]]
        at, found = lookup_sorted(new.ids, t.ids)
        t.rows[found] = rows[at[found]]
        if len(new.inconsistent):
            self.tracks = t.subset(~np.isin(t.ids, new.inconsistent))

    def _remap(self, remap: np.ndarray) -> None:
        """Follow the map's renumbering of points in the tracks (a track whose point went becomes a candidate)."""
        self.tracks.rows = remap[self.tracks.rows]

    def _adjust(self, K: np.ndarray, fixed_count: int) -> None:
        """Windowed bundle adjustment with the first `fixed_count` keyframes held; observations it finds wrong are
        dropped (and the tracks they came from when the newest keyframe made them), and points nobody sees."""
        m = self.map
        obs = m.observations(self.extractor.level_sigmas)
        if len(obs.point) == 0:
            return
        fixed = np.zeros(len(m.keyframes), bool)
        fixed[: min(fixed_count, len(m.keyframes) - 1)] = True
        poses = np.stack([kf.pose for kf in m.keyframes])
        poses, m.positions, _ = bundle_adjust(poses, fixed, m.positions, obs, K, self.config.ba_iterations,
                                              self.config.huber_sigmas)
        for kf, pose in zip(m.keyframes, poses, strict=True):
            kf.pose = pose
        bad = reprojection_chi2(poses, m.positions, obs, K) > self.config.chi2_px
        for slot, kf in enumerate(m.keyframes):
            bad_rows = obs.point[bad & (obs.keyframe == slot)]
            if len(bad_rows):
                kf.point_ids[np.isin(kf.point_ids, bad_rows)] = -1
        bad_newest = obs.point[bad & (obs.keyframe == len(m.keyframes) - 1)]
        if len(bad_newest):
            self.tracks = self.tracks.subset(~np.isin(self.tracks.rows, bad_newest))
        self._remap(m.forget_unobserved())

    def _normalise_scale(self) -> None:
        """Scale the map about the first keyframe so that its median point depth is 1."""
        first = self.map.keyframes[0]
        s = 1.0 / max(self._median_depth(first), 1e-9)
        m, origin = self.map, first.pose[:3, 3].copy()
        m.positions = origin + s * (m.positions - origin)
        for kf in m.keyframes:
            kf.pose = kf.pose.copy()
            kf.pose[:3, 3] = origin + s * (kf.pose[:3, 3] - origin)

    def _place(self, kf: Keyframe) -> Place:
        """The keyframe's ORB keypoints that lie on one of its map points' observations (within the relocalisation
        tolerance), with those points."""
        has = np.flatnonzero(kf.point_ids >= 0)
        orb = kf.orb
        if len(has) == 0 or len(orb) == 0:
            return Place(kf.index, kf.pose.copy(), orb.keypoints[:0], orb.descriptors[:0], np.zeros((0, 3)))
        d2 = ((orb.keypoints[:, None, :] - kf.features.keypoints[None, has, :]) ** 2).sum(-1)
        nearest = d2.argmin(axis=1)
        radius = self.config.place_radius_px * self.extractor.level_sigmas(orb.octaves)
        near = np.flatnonzero(d2[np.arange(len(orb)), nearest] <= radius ** 2)
        return Place(kf.index, kf.pose.copy(), orb.keypoints[near], orb.descriptors[near],
                     self.map.positions[kf.point_ids[has[nearest[near]]]].copy())

    def _retire(self, keyframes: list[Keyframe]) -> None:
        places = (self._place(kf) for kf in keyframes)
        self.retired.extend(p for p in places if len(p.points) >= self.config.reloc_min_inliers)
        del self.retired[: max(0, len(self.retired) - self.config.reloc_keyframes)]

    def _sparse_depth(self, kf: Keyframe, camera: Intrinsics) -> np.ndarray:
        """z-depth of the keyframe's points at their pixels, 0 elsewhere."""
        depth = np.zeros((camera.height, camera.width), np.float32)
        has = np.flatnonzero(kf.point_ids >= 0)
        z = to_camera(self.map.positions[kf.point_ids[has]], kf.pose)[:, 2]
        uv = kf.features.keypoints[has]
        col = np.clip(uv[:, 0].astype(np.int64), 0, camera.width - 1)
        row = np.clip(uv[:, 1].astype(np.int64), 0, camera.height - 1)
        keep = z > 0
        depth[row[keep], col[keep]] = z[keep]
        return depth

    # ---- losing and finding the way back ---------------------------------------------------------------------
    def _lose(self, index: int, reason: str) -> TrackingResult:
        self.status = "lost"
        self.lost_since = index
        self.velocity = np.eye(4)
        return TrackingResult(self.pose.copy(), tracked=False, keyframe_hint=False,
                              events=[{"type": "tracking_lost", "reason": reason, "frame": index}])

    def _relocalise(self, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult:
        """Back on track when most tracks of the last tracked frame are found again in this one (a short loss:
        bad frames, an occlusion); else place recognition over the remembered keyframes, where a hit starts a new
        local map from the place's points seen in this frame (their positions, hence the scale, carry over)."""
        c = self.config
        K = camera_matrix(camera)
        found = self._follow(gray, self.pose, K)
        if found is not None and found[2] >= c.recover_share * self.tracks.mapped.sum():
            pose, self.tracks, inliers = found
            self.previous_gray = gray
            event = {"type": "relocalized", "frame": index, "place": self.map.keyframes[-1].index,
                     "inliers": inliers, "lost_frames": index - (self.lost_since if self.lost_since is not None
                                                                  else index)}
            self.status, self.lost_since, self.velocity = "tracking", None, np.eye(4)
            return TrackingResult(pose, tracked=True, keyframe_hint=False, events=[event])
        still_lost = TrackingResult(self.pose.copy(), tracked=False, keyframe_hint=False)
        features = self.extractor.extract(gray)
        if len(features) < c.min_features:
            return still_lost
        places = self.retired + [self._place(kf) for kf in self.map.keyframes]
        hit = self.recognizer.relocalise(features, places, K, self.extractor.level_sigmas(features.octaves))
        if hit is None:
            return still_lost
        self._retire(self.map.keyframes)
        m = self.map = LocalMap()
        rows = m.add_points(hit.points, np.zeros((len(hit.points), 32), np.uint8))
        ids = np.arange(self.next_id, self.next_id + len(rows), dtype=np.int64)
        self.next_id += len(rows)
        self.tracks = Tracks(ids, features.keypoints[hit.keypoints].astype(np.float32), rows)
        kf = self._new_keyframe(index, hit.pose, gray)
        self.tracked_at_keyframe = len(rows)
        self.previous_gray = gray
        event = {"type": "relocalized", "frame": index, "place": hit.place, "inliers": len(rows),
                 "lost_frames": index - (self.lost_since if self.lost_since is not None else index)}
        self.status, self.lost_since, self.velocity = "tracking", None, np.eye(4)
        return TrackingResult(hit.pose, tracked=True, keyframe_hint=True, depth=self._sparse_depth(kf, camera),
                              events=[event])

    # ---- snapshots -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything to continue after a restart (msgpack-able; bounded by the window and the place memory)."""
        def image(gray: np.ndarray | None) -> np.ndarray:
            return np.zeros((0, 0), np.uint8) if gray is None else gray

        return {
            "version": STATE_VERSION, "config": self.config.model_dump(), "status": self.status,
            "pose": self.pose, "velocity": self.velocity, "frames_since_keyframe": self.frames_since_keyframe,
            "tracked_at_keyframe": self.tracked_at_keyframe,
            "lost_since": -1 if self.lost_since is None else self.lost_since,
            "image_size": [] if self.image_size is None else list(self.image_size),
            "focal": self.focal.state_dict(),
            "estimated_intrinsics": {} if self.estimated_intrinsics is None else self.estimated_intrinsics.to_dict(),
            "pending": [{"index": i, "ids": ids, "uv": uv} for i, ids, uv in self.pending],
            "previous_gray": image(self.previous_gray), "keyframe_gray": image(self.keyframe_gray),
            "tracks": self.tracks.to_state(), "next_id": self.next_id,
            "map": self.map.to_state(), "retired": [p.to_state() for p in self.retired],
            "engine_keyframes": [{"index": i, "pose": p} for i, p in self.engine_keyframes],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from `state_dict()` (the configuration comes with the state)."""
        if int(state.get("version", -1)) != STATE_VERSION:
            raise ValueError(f"visual odometry state version {state.get('version')!r}, expected {STATE_VERSION}")
        self.__init__(VisualOdometryConfig(**state["config"]))
        self.status = str(state["status"])
        self.pose = np.asarray(state["pose"], np.float64).reshape(4, 4)
        self.velocity = np.asarray(state["velocity"], np.float64).reshape(4, 4)
        self.frames_since_keyframe = int(state["frames_since_keyframe"])
        self.tracked_at_keyframe = int(state["tracked_at_keyframe"])
        self.lost_since = None if int(state["lost_since"]) < 0 else int(state["lost_since"])
        self.image_size = tuple(int(v) for v in state["image_size"]) or None
        self.focal.load_state_dict(state["focal"])
        if state["estimated_intrinsics"]:
            self.estimated_intrinsics = Intrinsics.from_dict(state["estimated_intrinsics"])
        self.pending = [(int(p["index"]), np.asarray(p["ids"], np.int64).reshape(-1),
                         np.asarray(p["uv"], np.float32).reshape(-1, 2)) for p in state["pending"]]
        for name in ("previous_gray", "keyframe_gray"):
            gray = np.asarray(state[name], np.uint8)
            setattr(self, name, np.ascontiguousarray(gray) if gray.size else None)
        self.tracks = Tracks.from_state(state["tracks"])
        self.next_id = int(state["next_id"])
        self.map = LocalMap.from_state(state["map"])
        self.retired = [Place.from_state(p) for p in state["retired"]]
        self.engine_keyframes.extend((int(k["index"]), np.asarray(k["pose"], np.float64).reshape(4, 4))
                                     for k in state.get("engine_keyframes", []))
