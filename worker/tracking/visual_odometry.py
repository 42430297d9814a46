"""Monocular visual odometry as a pose source: ORB features, two-view initialisation, PnP tracking against a local
map with a constant-velocity prior, keyframes that triangulate new points, windowed bundle adjustment, and
relocalisation by place recognition when tracking is lost.

Poses are camera-to-world rigid 4x4 matrices (a Sim(3) with s = 1); the world is the camera of the frame the map
was initialised from and the scale makes that map's median depth 1.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics

from .base import TrackingResult
from .bundle_adjustment import bundle_adjust, reprojection_chi2
from .features import Features, OrbExtractor
from .local_map import Keyframe, LocalMap
from .matching import match_by_projection, ratio_matches
from .pose_optimization import optimize_pose
from .projection import camera_matrix, in_image, invert_pose, project, to_camera
from .relocalization import Place, PlaceRecognizer
from .self_calibration import FocalEstimator
from .triangulation import good_points, triangulate
from .two_view import initialise_two_view
from .vo_config import VisualOdometryConfig

STATE_VERSION = 1


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
        self.pending: list[tuple[int, Features]] = []  # frames waiting for initialisation; [0] is the reference
        self.pose = np.eye(4)
        self.velocity = np.eye(4)  # camera motion of the last frame (previous^-1 @ current)
        self.frames_since_keyframe = 0
        self.tracked_at_keyframe = 0
        self.lost_since: int | None = None
        self.image_size: tuple[int, int] | None = None
        self.estimated_intrinsics: Intrinsics | None = None
        self.focal = FocalEstimator(self.config)

    # ---- PoseSource ------------------------------------------------------------------------------------------
    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        """Track the next frame (see the module docstring); bad frames lose tracking, they never raise."""
        camera = self._camera(frame, intrinsics)
        gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
        features = self.extractor.extract(gray)
        if self.status == "initializing":
            result = self._initialise(frame.index, features, camera, intrinsics is None)
        elif self.status == "lost":
            result = self._relocalise(frame.index, features, camera)
        else:
            result = self._track(frame.index, features, camera)
        if not np.all(np.isfinite(result.pose)):  # never hand out a NaN pose, whatever happened above
            result = self._lose(frame.index, "non-finite pose estimate")
        self.pose = result.pose
        return result

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The engine's keyframes do not change VO's own (it keeps its keyframes for its map)."""

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

    def _sigma(self, features: Features) -> np.ndarray:
        return self.extractor.level_sigmas(features.octaves)

    # ---- initialisation --------------------------------------------------------------------------------------
    def _initialise(self, index: int, features: Features, camera: Intrinsics, uncalibrated: bool
                    ) -> TrackingResult:
        c = self.config
        waiting = TrackingResult(np.eye(4), tracked=True, keyframe_hint=False)
        if len(features) < c.min_features:
            return waiting
        if not self.pending:
            self.pending.append((index, features))
            return waiting
        ref_index, ref = self.pending[0]
        if uncalibrated and not self.focal.frozen:
            self.focal.observe(ref, features, camera)
            camera = self.estimated_intrinsics = self.focal.intrinsics(camera.width, camera.height)
        K = camera_matrix(camera)
        attempt = initialise_two_view(ref, features, K, c, self._sigma(ref), self._sigma(features))
        if attempt.map is None:
            if attempt.matches < c.init_min_matches:  # the view has moved on: start again from this frame
                self.pending = [(index, features)]
            else:
                self.pending.append((index, features))
                if len(self.pending) > c.init_max_frames:
                    self.pending.pop(0)
            return waiting
        self.focal.freeze()
        two = attempt.map
        m = self.map = LocalMap()
        rows = m.add_points(two.points, features.descriptors[two.ib])
        kf_a = Keyframe(ref_index, np.eye(4), ref, np.full(len(ref), -1, np.int64))
        kf_b = Keyframe(index, two.pose_b, features, np.full(len(features), -1, np.int64))
        kf_a.point_ids[two.ia], kf_b.point_ids[two.ib] = rows, rows
        m.keyframes = [kf_a, kf_b]
        self._adjust(K)
        self._normalise_scale()
        pose = m.keyframes[-1].pose
        between = [[ref_index, np.eye(4).tolist()]]
        previous = np.eye(4)
        for n, (i, f) in enumerate(self.pending[1:], start=1):
            previous = self._pose_between(f, n / len(self.pending), pose, K)
            between.append([i, previous.tolist()])
        self.pending = []
        self.velocity = invert_pose(previous) @ pose
        self.status = "tracking"
        self.frames_since_keyframe = 0
        self.tracked_at_keyframe = int((kf_b.point_ids >= 0).sum())
        event = {"type": "initialized", "frame": index, "frames": between, "points": len(m),
                 "parallax_deg": round(two.parallax_deg, 3)}
        if uncalibrated:
            event["intrinsics"] = camera.to_dict()
        return TrackingResult(pose, tracked=True, keyframe_hint=True, depth=self._sparse_depth(kf_b, camera),
                              events=[event])

    def _pose_between(self, features: Features, fraction: float, pose_b: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Pose of a frame between the two initial views: tracked against the new map from the interpolated guess."""
        rotvec = cv2.Rodrigues(pose_b[:3, :3])[0].ravel() * fraction
        guess = np.eye(4)
        guess[:3, :3], guess[:3, 3] = cv2.Rodrigues(rotvec)[0], pose_b[:3, 3] * fraction
        tracked = self._track_local_map(features, guess, K, self.config.wide_search_radius)
        return guess if tracked is None else tracked[0]

    # ---- tracking --------------------------------------------------------------------------------------------
    def _search(self, features: Features, pose: np.ndarray, K: np.ndarray, radius: float, count: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
        """Guided matches (point rows, keypoint indices) of the local map projected at `pose`."""
        m = self.map
        uv, z = project(m.positions, pose, K)
        w, h = self.image_size
        visible = np.flatnonzero(in_image(uv, z, w, h))
        if count:
            m.visible[visible] += 1
        kp = match_by_projection(uv[visible], m.descriptors[visible], np.full(len(visible), radius), features,
                                 self.config.max_hamming, self.config.match_ratio)
        found = kp >= 0
        return visible[found], kp[found]

    def _track_local_map(self, features: Features, guess: np.ndarray, K: np.ndarray, radius: float
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(pose, point rows, keypoint indices) of inliers after two rounds of search + pose refinement."""
        c = self.config
        pose = guess
        for n, r in enumerate((radius, max(4.0, 0.5 * c.search_radius))):
            rows, kps = self._search(features, pose, K, r, count=n == 1)
            if len(rows) < c.min_tracked:
                return None
            pose, inlier = optimize_pose(pose, self.map.positions[rows], features.keypoints[kps].astype(np.float64),
                                         self._sigma(features)[kps], K, c.chi2_px)
            if inlier.sum() < c.min_tracked or not np.all(np.isfinite(pose)):
                return None
        return pose, rows[inlier], kps[inlier]

    def _track(self, index: int, features: Features, camera: Intrinsics) -> TrackingResult:
        c = self.config
        if len(features) < c.min_features:
            return self._lose(index, f"{len(features)} keypoints < {c.min_features} (dark, textureless or blurred)")
        K = camera_matrix(camera)
        predicted = self.pose @ self.velocity
        tracked = None
        for guess, radius in ((predicted, c.search_radius), (predicted, c.wide_search_radius),
                              (self.pose, c.wide_search_radius)):
            tracked = self._track_local_map(features, guess, K, radius)
            if tracked is not None:
                break
        if tracked is None:
            return self._lose(index, "too few map points matched (sudden motion, occlusion or a new view)")
        pose, rows, kps = tracked
        self.map.found[rows] += 1
        self.velocity = invert_pose(self.pose) @ pose
        self.frames_since_keyframe += 1
        if not self._needs_keyframe(pose, len(rows)):
            return TrackingResult(pose, tracked=True, keyframe_hint=False)
        kf = self._insert_keyframe(index, pose, features, rows, kps, K)
        self.velocity = invert_pose(self.pose) @ kf.pose
        return TrackingResult(kf.pose, tracked=True, keyframe_hint=True, depth=self._sparse_depth(kf, camera))

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
    def _insert_keyframe(self, index: int, pose: np.ndarray, features: Features, rows: np.ndarray, kps: np.ndarray,
                         K: np.ndarray) -> Keyframe:
        m = self.map
        point_ids = np.full(len(features), -1, np.int64)
        point_ids[kps] = rows
        m.descriptors[rows] = features.descriptors[kps]  # the latest look of a point matches the next frames best
        kf = Keyframe(index, pose.copy(), features, point_ids)
        neighbours = m.keyframes[-self.config.triangulation_neighbours:][::-1]
        m.keyframes.append(kf)
        for other in neighbours:
            self._triangulate(kf, other, K)
        self._retire(m.slide(self.config.window + self.config.fixed_keyframes))
        m.forget((m.observation_counts() == 0) | ((m.visible >= 6) & (m.found < 0.25 * m.visible)))
        self._adjust(K)
        self.frames_since_keyframe = 0
        self.tracked_at_keyframe = int((kf.point_ids >= 0).sum())
        return kf

    def _triangulate(self, kf: Keyframe, other: Keyframe, K: np.ndarray) -> None:
        c = self.config
        free_a = np.flatnonzero(kf.point_ids < 0)
        free_b = np.flatnonzero(other.point_ids < 0)
        ia, ib = ratio_matches(kf.features.descriptors[free_a], other.features.descriptors[free_b], c.match_ratio,
                               c.max_hamming)
        a, b = free_a[ia], free_b[ib]
        uv_a, uv_b = kf.features.keypoints[a].astype(np.float64), other.features.keypoints[b].astype(np.float64)
        points = triangulate(kf.pose, other.pose, uv_a, uv_b, K)
        ok = good_points(points, kf.pose, other.pose, uv_a, uv_b, self._sigma(kf.features)[a],
                         self._sigma(other.features)[b], K, c.chi2_px, c.min_parallax_deg)
        rows = self.map.add_points(points[ok], kf.features.descriptors[a[ok]])
        kf.point_ids[a[ok]] = rows
        other.point_ids[b[ok]] = rows

    def _adjust(self, K: np.ndarray) -> None:
        """Windowed bundle adjustment; observations it finds wrong are dropped, and points nobody sees."""
        m = self.map
        obs = m.observations(self.extractor.level_sigmas)
        if len(obs.point) == 0:
            return
        fixed = np.zeros(len(m.keyframes), bool)
        # Keyframes older than the adjusted window stay fixed and anchor pose and scale. A young map fixes only its
        # first camera; its scale is then free, so the map's spread about that camera is restored afterwards.
        fixed[: max(1, len(m.keyframes) - self.config.window)] = True
        origin = m.keyframes[0].pose[:3, 3].copy()
        spread = float(np.median(np.linalg.norm(m.positions - origin, axis=1)))
        poses = np.stack([kf.pose for kf in m.keyframes])
        poses, m.positions, _ = bundle_adjust(poses, fixed, m.positions, obs, K, self.config.ba_iterations,
                                              self.config.huber_sigmas)
        for kf, pose in zip(m.keyframes, poses, strict=True):
            kf.pose = pose
        if fixed.sum() == 1:
            self._rescale(origin, spread / max(float(np.median(np.linalg.norm(m.positions - origin, axis=1))), 1e-12))
            poses = np.stack([kf.pose for kf in m.keyframes])
        bad = reprojection_chi2(poses, m.positions, obs, K) > self.config.chi2_px
        for slot, kp_rows in ((s, obs.point[bad & (obs.keyframe == s)]) for s in range(len(m.keyframes))):
            if len(kp_rows):
                kf = m.keyframes[slot]
                kf.point_ids[np.isin(kf.point_ids, kp_rows)] = -1
        m.forget_unobserved()

    def _normalise_scale(self) -> None:
        """Scale the map about the first keyframe so that its median point depth is 1."""
        first = self.map.keyframes[0]
        self._rescale(first.pose[:3, 3].copy(), 1.0 / max(self._median_depth(first), 1e-9))

    def _rescale(self, origin: np.ndarray, s: float) -> None:
        """Scale points and keyframe positions about `origin` by s."""
        m = self.map
        m.positions = origin + s * (m.positions - origin)
        for kf in m.keyframes:
            kf.pose = kf.pose.copy()
            kf.pose[:3, 3] = origin + s * (kf.pose[:3, 3] - origin)

    def _place(self, kf: Keyframe) -> Place:
        has = np.flatnonzero(kf.point_ids >= 0)
        return Place(kf.index, kf.pose.copy(), kf.features.keypoints[has], kf.features.descriptors[has],
                     self.map.positions[kf.point_ids[has]].copy())

    def _retire(self, keyframes: list[Keyframe]) -> None:
        self.retired.extend(self._place(kf) for kf in keyframes if (kf.point_ids >= 0).sum() > 0)
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

    def _relocalise(self, index: int, features: Features, camera: Intrinsics) -> TrackingResult:
        c = self.config
        still_lost = TrackingResult(self.pose.copy(), tracked=False, keyframe_hint=False)
        if len(features) < c.min_features:
            return still_lost
        K = camera_matrix(camera)
        places = self.retired + [self._place(kf) for kf in self.map.keyframes]
        hit = self.recognizer.relocalise(features, places, K, self._sigma(features))
        if hit is None:
            return still_lost
        tracked = self._track_local_map(features, hit.pose, K, c.search_radius)
        keyframe_hint, depth = False, None
        if tracked is not None:
            pose, rows, _ = tracked
            self.map.found[rows] += 1
            inliers = len(rows)
        else:  # the local map does not cover this place: start a new one from the place's points
            self._retire(self.map.keyframes)
            m = self.map = LocalMap()
            pose = hit.pose
            rows = m.add_points(hit.points, features.descriptors[hit.keypoints])
            kf = Keyframe(index, pose.copy(), features, np.full(len(features), -1, np.int64))
            kf.point_ids[hit.keypoints] = rows
            m.keyframes = [kf]
            inliers = len(rows)
            self.frames_since_keyframe = 0
            self.tracked_at_keyframe = inliers
            keyframe_hint, depth = True, self._sparse_depth(kf, camera)
        event = {"type": "relocalized", "frame": index, "place": hit.place, "inliers": inliers,
                 "lost_frames": index - (self.lost_since if self.lost_since is not None else index)}
        self.status, self.lost_since, self.velocity = "tracking", None, np.eye(4)
        return TrackingResult(pose, tracked=True, keyframe_hint=keyframe_hint, depth=depth, events=[event])

    # ---- snapshots -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything to continue after a restart (msgpack-able; bounded by the window and the place memory)."""
        return {
            "version": STATE_VERSION, "config": self.config.model_dump(), "status": self.status,
            "pose": self.pose, "velocity": self.velocity, "frames_since_keyframe": self.frames_since_keyframe,
            "tracked_at_keyframe": self.tracked_at_keyframe,
            "lost_since": -1 if self.lost_since is None else self.lost_since,
            "image_size": [] if self.image_size is None else list(self.image_size),
            "focal": self.focal.state_dict(),
            "estimated_intrinsics": {} if self.estimated_intrinsics is None else self.estimated_intrinsics.to_dict(),
            "pending": [{"index": i, "features": f.to_state()} for i, f in self.pending],
            "map": self.map.to_state(), "retired": [p.to_state() for p in self.retired],
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
        self.pending = [(int(p["index"]), Features.from_state(p["features"])) for p in state["pending"]]
        self.map = LocalMap.from_state(state["map"])
        self.retired = [Place.from_state(p) for p in state["retired"]]
