"""Monocular visual odometry as a pose source.

Points are followed from frame to frame by sub-pixel optical flow (Lucas-Kanade, forward-backward checked, guided
by the motion model) and re-matched against the last keyframe's image, so that small errors do not add up from frame
to frame. The map starts from a two-view reconstruction of the first tracks with enough parallax; each frame's pose
then comes from the tracks that measure map points (robust refinement from the constant-velocity guess, PnP + RANSAC
when that fails). Keyframes are taken when tracks drop or the baseline grows: they add new corners, triangulate the
candidate tracks that gained enough parallax since the oldest keyframe that saw them, and run a local bundle
adjustment over the keyframes sharing the most points with the new one, those that also see their points held
fixed (`covisibility`), so scale carries over without rescaling. A lost frame first tries to take up the last
tracked frame's tracks (a short loss), then place recognition with the ORB features the keyframes keep, then a map
restarted from two views. A restarted map is joined to the older one, scale included, when one of its keyframes
recognises an older keyframe (`map_join`: the map moves, the poses handed out do not jump, and the `maps_merged`
event carries the Sim(3) edge for the pose graph). When the camera comes back, a keyframe VO takes for its own map
is not offered to the engine (`keyframe_hint=False`) if an engine keyframe at least `reuse_min_age` frames old lies
near and sees most of the frame's tracked map points: a place walked through again keeps the keyframes of its first
visit. A turn faster than points can be triangulated is followed by the rotation the tracks agree on
(`rotation_only`); where too few tracks survive (stripes, a plain wall, blur) the whole image is aligned to the last
tracked frame's (`direct_rotation`: the turn measured, the position predicted), and only then is the frame lost.

Poses are camera-to-world rigid 4x4 matrices (a Sim(3) with s = 1); the world is the camera of the frame the map
was initialised from and the scale makes that map's median depth 1. Poses handed out are the map's moved by the
output similarity (the identity until a restarted map is joined to an older one).
"""

from __future__ import annotations

from collections import deque
from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics

from . import schur_native
from .base import TrackingResult
from .covisibility import LocalWindow
from .local_map import LocalMap
from .map_join import (
    similarity_scale,
)
from .optical_flow import predicted_pixels
from .pose_optimization import pnp_pose
from .projection import camera_matrix, invert_pose, rigid
from .relocalization import Place
from .tracks import Tracks, lookup_sorted
from .two_view import two_view_from_matches
from .vo_calibration import camera_of
from .vo_config import VisualOdometryConfig
from .vo_frame_tracking import (
    follow,
    track_frame,
)
from .vo_initialisation import initialise, two_keyframe_map
from .vo_map_join import join_maps, output_is_identity, to_output
from .vo_mapping import (
    adjust,
    median_depth,
    move_map,
    new_keyframe,
    sparse_depth,
)
from .vo_places import learned_candidates, orb_features, place_of, retire
from .vo_state import STATE_VERSION, Anchor, JoinState, VoParts, VoState
from .vo_tracks import flow, replenish
from .xfeat import XFeatures, mutual_matches


class VisualOdometry:
    """PoseSource for RGB-only streams (see the module docstring)."""

    name = "visual_odometry"
    submap_seam = "new_map"  # the pose-graph edge kind between a lost map and the new map begun after it

    def __init__(self, config: VisualOdometryConfig | None = None) -> None:
        self.config = config or VisualOdometryConfig()
        self.parts = VoParts.build(self.config)
        self.extractor, self.recognizer, self.learned = self.parts.extractor, self.parts.recognizer, self.parts.learned
        schur_native.available()  # builds (or loads) the compiled kernel now, not at the first keyframe
        self._reset()

    def _reset(self) -> None:
        self.state = VoState.start(self.config)

    # ---- what callers read (the state's, read-only here) -----------------------------------------------------
    @property
    def status(self) -> str:
        return self.state.status

    @property
    def pose(self) -> np.ndarray:
        return self.state.pose

    @property
    def estimated_intrinsics(self) -> Intrinsics | None:
        return self.state.estimated_intrinsics

    @property
    def map(self) -> LocalMap:
        return self.state.map

    @property
    def map_id(self) -> int:
        return self.state.map_id

    @property
    def map_depth(self) -> float:
        return self.state.map_depth

    @property
    def join(self) -> JoinState | None:
        return self.state.join

    @property
    def anchor(self) -> Anchor | None:
        return self.state.anchor

    @property
    def retired(self) -> list[Place]:
        return self.state.retired

    @property
    def keyframe_images(self) -> dict[int, np.ndarray]:
        return self.state.keyframe_images

    @property
    def engine_keyframes(self) -> deque[tuple[int, np.ndarray]]:
        return self.state.engine_keyframes

    # ---- PoseSource ------------------------------------------------------------------------------------------
    def track(self, frame: Frame, intrinsics: Intrinsics | None, motion_guess: np.ndarray | None = None
              ) -> TrackingResult:
        """Track the next frame (see the module docstring); bad frames lose tracking, they never raise.
        `motion_guess` (previous^-1 @ current in this odometry's units, e.g. a device's relative motion) replaces
        the constant-velocity guess when given."""
        s = self.state
        camera = camera_of(s, frame, intrinsics)
        gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
        self.learned.begin_frame(frame.index)
        if motion_guess is not None and not output_is_identity(s):  # output units -> the map's
            motion_guess = np.array(motion_guess, np.float64)
            motion_guess[:3, 3] /= similarity_scale(s.output)
        if s.status == "initializing":
            # after a loss, the old map's places are looked for while the new map waits to be made
            found = self._recognise_place(frame.index, gray, camera) if s.maps_started > 1 and s.retired else None
            if found is not None:
                s.maps_started -= 1  # back on the old map: the new one was never made
                s.pending, s.pending_orientation, s.init_state = [], {}, ""
            result = found or initialise(s, self.parts, frame.index, gray, camera, intrinsics is None)
        elif s.status == "lost":
            result = self._relocalise(frame.index, gray, camera)
        else:
            result = track_frame(s, self.parts, frame.index, gray, camera, motion_guess)
            if isinstance(result, str):  # lost: a map may restart from the last tracked frame at once
                result = self._lose_or_restart(frame.index, gray, camera, result)
        if not np.all(np.isfinite(result.pose)):  # never hand out a NaN pose, whatever happened above
            result = self._lose(frame.index, "non-finite pose estimate")
        s.pose = result.pose
        if result.tracked:
            s.last_tracked = frame.index
        result.submap_id = s.maps_started - 1
        return to_output(s, result)

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The engine's keyframes do not change VO's own; they are remembered as places to come back to."""
        s = self.state
        if self.config.reuse_keyframes > 0:
            s.engine_keyframes.append((int(frame.index), np.asarray(pose, np.float64).copy()))

    # ---- camera ----------------------------------------------------------------------------------------------

    # ---- optical flow ----------------------------------------------------------------------------------------

    # ---- initialisation --------------------------------------------------------------------------------------

    # ---- tracking --------------------------------------------------------------------------------------------

    # ---- keyframes and the map -------------------------------------------------------------------------------

    # ---- joining a restarted map to an older one -------------------------------------------------------------

    # ---- losing and finding the way back ---------------------------------------------------------------------
    def _lose_or_restart(self, index: int, gray: np.ndarray, camera: Intrinsics, reason: str) -> TrackingResult:
        """Lose tracking; when a map restarts from the last tracked frame at once, this frame is tracked on it
        (both events are reported: the old map's tracks broke here)."""
        lost = self._lose(index, reason)
        restarted = self._reinitialise(index, gray, camera) or self._relocalise_learned(index, gray, camera)
        if restarted is None:
            return lost
        restarted.events = lost.events + restarted.events
        return restarted

    def _lose(self, index: int, reason: str) -> TrackingResult:
        """Tracking is lost: the held pose, and the last tracked frame kept as the anchor a map may restart from
        (when the loss breaks tracking, not a restart or an initialisation)."""
        s = self.state
        was_tracking = s.status == "tracking"
        if was_tracking:
            s.mapped_at_loss = int(s.tracks.mapped.sum())
        s.status = "lost"
        s.lost_since, s.rotation_since, s.direct_since = index, None, None
        s.anchor = None
        if self.config.reinit_after_loss and s.previous_gray is not None and was_tracking:
            replenish(s, self.parts, s.previous_gray)  # the anchor's corners, not only its surviving tracks
            t = s.tracks
            points = np.full((len(t), 3), np.nan)
            points[t.mapped] = s.map.positions[t.rows[t.mapped]]
            s.anchor = Anchor(s.last_tracked, s.pose.copy(), t.ids.copy(), t.uv.copy(), points,
                              s.velocity.copy(), s.pose.copy(), s.previous_gray)
        s.velocity = np.eye(4)
        return TrackingResult(s.pose.copy(), tracked=False, keyframe_hint=False, quality=0.0,
                              events=[{"type": "tracking_lost", "reason": reason, "frame": index}])

    def _relocalise(self, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult:
        """Back on track when most tracks of the last tracked frame are found again in this one (a short loss:
        bad frames, an occlusion); else place recognition over the remembered keyframes, where a hit starts a new
        local map from the place's points seen in this frame (their positions, hence the scale, carry over)."""
        s = self.state
        c = self.config
        K = camera_matrix(camera)
        found = follow(s, self.parts, gray, s.pose, K)
        # Measured against the tracks at the loss: those followed through the lost frames are fewer.
        if found is not None and found[2] >= c.recover_share * max(s.mapped_at_loss, s.tracks.mapped.sum()):
            pose, s.tracks, inliers = found
            s.previous_gray = gray
            event = {"type": "relocalized", "frame": index, "place": s.map.keyframes[-1].index,
                     "inliers": inliers, "lost_frames": index - (s.lost_since if s.lost_since is not None
                                                                 else index)}
            s.status, s.lost_since, s.velocity, s.anchor = "tracking", None, np.eye(4), None
            return TrackingResult(pose, tracked=True, keyframe_hint=False, events=[event],
                                  quality=min(1.0, inliers / max(s.tracked_at_keyframe, 1)))
        recognised = self._recognise_place(index, gray, camera)
        if recognised is not None:
            return recognised
        restarted = self._reinitialise(index, gray, camera) or self._relocalise_learned(index, gray, camera)
        if restarted is not None:
            return restarted
        lost_for = index - (s.lost_since if s.lost_since is not None else index)
        if c.new_map_after_lost and lost_for >= c.new_map_after_lost and self._textured(index, gray):
            return self._begin_new_map(index, gray, camera, lost_for)
        return TrackingResult(s.pose.copy(), tracked=False, keyframe_hint=False, quality=0.0)

    def _recognise_place(self, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult | None:
        """Place recognition over the remembered keyframes (ORB, verified by PnP): a hit starts a new local map
        from the place's points seen in this frame (their positions, hence the scale, carry over); None: no hit."""
        s = self.state
        features = orb_features(s, self.parts, index, gray)
        if len(features) < self.config.min_features:
            return None
        places = s.retired + [place_of(s, self.parts, kf) for kf in s.map.keyframes]
        hit = self.recognizer.relocalise(features, places, camera_matrix(camera),
                                         self.extractor.level_sigmas(features.octaves))
        if hit is None:
            return None
        return self._restart_from(index, gray, camera, hit.pose, features.keypoints[hit.keypoints], hit.points,
                                  hit.place, "place recognition")

    def _textured(self, index: int, gray: np.ndarray) -> bool:
        """Whether the frame has the features an initialisation needs, and at least 30 % of the last keyframe's (a
        covered lens or a blurred frame begins no map)."""
        s = self.state
        keyframes = s.map.keyframes
        usual = len(keyframes[-1].features.keypoints) if keyframes else 0
        return len(orb_features(s, self.parts, index, gray)) >= max(self.config.init_min_matches, 0.3 * usual)

    def _begin_new_map(self, index: int, gray: np.ndarray, camera: Intrinsics, lost_for: int) -> TrackingResult:
        """Give up finding the old map from here: its keyframes become places, and a new map initialises from
        this frame on, placed at the last pose with the old map's median scene depth (a guess: the two share no
        point) until a loop or relocalisation joins them. A `new_map` event says so."""
        s = self.state
        depth = median_depth(s, s.map.keyframes[-1]) if s.map.keyframes else s.map_depth
        retire(s, self.parts, s.map.keyframes)
        s.map, s.tracks, s.anchor = LocalMap(), Tracks.empty(), None
        s.pending, s.pending_orientation, s.init_state = [], {}, ""
        s.previous_gray = s.keyframe_gray = None
        s.velocity = np.eye(4)
        s.frames_since_keyframe = s.tracked_at_keyframe = 0
        s.map_origin, s.map_depth = s.pose.copy(), depth
        s.maps_started += 1
        if self.config.join_maps:  # joined to an older map once one of its keyframes recognises an older place
            s.map_id, s.maps_made, s.join = s.maps_made, s.maps_made + 1, JoinState(index)
        s.status, s.lost_since = "initializing", None
        result = initialise(s, self.parts, index, gray, camera, uncalibrated=False)
        result.events = [{"type": "new_map", "frame": index, "map": s.maps_started, "lost_frames": lost_for,
                          "scene_depth": round(depth, 4)}] + list(result.events or [])
        return result

    def _restart_from(self, index: int, gray: np.ndarray, camera: Intrinsics, pose: np.ndarray, uv: np.ndarray,
                      points: np.ndarray, place: int, method: str) -> TrackingResult:
        """A new local map from the old map's points (world [n, 3]) seen at pixels uv [n, 2] of this frame, posed
        at `pose` (their positions, hence the scale, carry over); the old keyframes become places."""
        s = self.state
        s.anchor = None
        retire(s, self.parts, s.map.keyframes)
        place_map = next((p.map_id for p in s.retired if p.index == place), s.map_id)
        if place_map != s.map_id:  # back in an older map's frame: its points carry that map's coordinates
            s.map_id, s.join = place_map, None
        m = s.map = LocalMap()
        rows = m.add_points(points, np.zeros((len(points), 32), np.uint8))
        ids = np.arange(s.next_id, s.next_id + len(rows), dtype=np.int64)
        s.next_id += len(rows)
        s.tracks = Tracks(ids, np.asarray(uv, np.float32).reshape(-1, 2), rows)
        kf = new_keyframe(s, self.parts, index, pose, gray)
        s.tracked_at_keyframe = len(rows)
        s.previous_gray = gray
        event = {"type": "relocalized", "frame": index, "place": place, "inliers": len(rows), "method": method,
                 "lost_frames": index - (s.lost_since if s.lost_since is not None else index)}
        s.status, s.lost_since, s.velocity = "tracking", None, np.eye(4)
        return TrackingResult(pose, tracked=True, keyframe_hint=True, depth=sparse_depth(s, kf, camera),
                              events=[event], quality=1.0)

    def _relocalise_learned(self, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult | None:
        """XFeat matching of this frame to the anchor's map points (the last tracked frame) and then to remembered
        keyframes (`_learned_candidates`), each verified by PnP + RANSAC and the robust refinement: the old map,
        hence its scale, carries on past a turn too fast for optical flow and ORB (None: not found). Runs on every
        `learned_reloc_every`-th lost frame, the first one included, within the frame's network passes
        (`learned_passes_per_frame`: what is not described yet waits for the next try)."""
        s = self.state
        c = self.config
        if not c.learned_relocalisation:
            return None
        since = s.lost_since if s.lost_since is not None else index
        if (index - since) % c.learned_reloc_every:  # the network costs more than a tracked frame
            return None
        K = camera_matrix(camera)
        current: XFeatures | None = None
        anchor = s.anchor
        if anchor is not None and index - anchor.index > c.learned_reloc_frames:
            s.anchor = anchor = None
        if anchor is not None and anchor.gray.size:
            if anchor.descriptors.size == 0 and not anchor.described:
                anchor.descriptors, anchor.world = self._learned_place(anchor)
            current = self.learned.of_frame(index, gray)
            if current is not None and len(anchor.world) >= c.reloc_min_inliers:
                ia, ib = mutual_matches(anchor.descriptors, current.descriptors, c.learned_min_similarity)
                if len(ia) >= c.reloc_min_inliers:
                    X, uv = anchor.world[ia], current.keypoints[ib].astype(np.float64)
                    found = pnp_pose(X, uv, K, np.full(len(X), 2.0), c.chi2_px, c.reloc_min_inliers)
                    if found is not None:
                        pose, inlier = found
                        return self._restart_from(index, gray, camera, pose, uv[inlier], X[inlier], anchor.index,
                                                  "learned")
        candidates = learned_candidates(s, self.parts, index, gray)
        if not candidates:
            return None
        current = self.learned.of_frame(index, gray, orb_features(s, self.parts, index, gray).keypoints)
        if current is None:
            return None
        hit = self.learned.relocalise(current, candidates, K, c.learned_keyframe_min_inliers)
        if hit is not None:
            return self._restart_from(index, gray, camera, hit.pose, current.keypoints[hit.keypoints], hit.points,
                                      hit.place, "learned keyframe")
        # Wide baselines: LighterGlue on every candidate, also those the pass budget left undescribed this frame (a
        # jump's lost frames may be few: the fox's are, before a new map begins).
        glue = c.learned_glue and self.learned.glue_due(index, c.learned_glue_every)
        glued = self.learned.glue_relocalise(gray, candidates, K, c.learned_keyframe_min_inliers) if glue else None
        if glued is None:
            return None
        hit, uv = glued
        return self._restart_from(index, gray, camera, hit.pose, uv[hit.keypoints], hit.points, hit.place,
                                  "learned glue")

    def _learned_place(self, anchor: Anchor) -> tuple[np.ndarray, np.ndarray]:
        """XFeat descriptors [n, 64] of the anchor image's keypoints that lie on one of its tracked map points
        (within `place_radius_px`), and those points [n, 3] (none while the frame has no network pass left)."""
        found = self.learned.describe_image(anchor.gray)
        anchor.described = found is not None
        has = np.isfinite(anchor.points).all(axis=1)
        if found is None or len(found) == 0 or not has.any():
            return np.zeros((0, 64), np.float32), np.zeros((0, 3))
        d2 = ((found.keypoints[:, None, :] - anchor.uv[None, has, :]) ** 2).sum(-1)
        nearest = d2.argmin(axis=1)
        near = np.flatnonzero(d2[np.arange(len(found)), nearest] <= (2.0 * self.config.place_radius_px) ** 2)
        return found.descriptors[near], anchor.points[has][nearest[near]]

    def _reinitialise(self, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult | None:
        """A new map from a two-view reconstruction between the last tracked frame (the anchor, whose pose is
        known) and this one, placed at the anchor and scaled by the old map points the two share (else by the
        old map's depth at the anchor); None while that fails. The anchor's tracks are followed meanwhile."""
        s = self.state
        c = self.config
        anchor = s.anchor
        if anchor is None:
            return None
        K = camera_matrix(camera)
        t = s.tracks
        predicted = rigid(anchor.predicted @ anchor.velocity)  # the motion model guides the flow while lost
        rows = np.where(t.rows < len(s.map), t.rows, -1)
        mapped = rows >= 0
        guess = predicted_pixels(t.uv, s.map.positions[rows[mapped]], mapped, anchor.predicted, predicted, K)
        uv, ok = flow(s, self.parts, gray, guess)
        if ok.sum() < 0.5 * len(t):
            uv_plain, ok_plain = flow(s, self.parts, gray, None)
            if ok_plain.sum() > ok.sum():
                uv, ok = uv_plain, ok_plain
        followed = Tracks(t.ids[ok], uv[ok], t.rows[ok])
        at, found = lookup_sorted(anchor.ids, followed.ids)
        common = np.flatnonzero(found)
        if len(common) < c.reinit_min_matches:  # the flow lost the anchor's view: its tracks stay those of the
            return None  # last frame they were followed into (learned matching may still find it)
        anchor.predicted = predicted
        s.tracks, s.previous_gray = followed, gray
        ones = np.ones(len(common))
        settings = c.model_copy(update={"init_min_parallax_deg": c.reinit_min_parallax_deg,
                                        "init_min_matches": c.reinit_min_matches,
                                        "init_min_points": min(c.init_min_points, c.reinit_min_matches)})
        attempt = two_view_from_matches(anchor.uv[at[common]], s.tracks.uv[common], K, settings, ones, ones,
                                        common, common)
        if attempt.map is None:
            return None
        two = attempt.map
        if attempt.model == "homography" and two.parallax_deg < c.init_min_parallax_deg:
            return None  # a turn in place fits a homography too, and noise then passes for a small baseline
        scale, shared = anchor.scale_of(two.points, at[two.ib])
        retire(s, self.parts, s.map.keyframes)
        if c.join_maps:  # a map of its own until a place of the old one is recognised
            s.map_id, s.maps_made, s.join = s.maps_made, s.maps_made + 1, JoinState(index)
        kf = two_keyframe_map(s, self.parts, index, gray, two, anchor.index, anchor.ids, anchor.uv)
        adjust(s, self.parts, K, LocalWindow(np.array([1]), np.array([0])))
        move_map(s, anchor.pose, scale)
        s.anchor = None
        s.tracked_at_keyframe = int(s.tracks.mapped.sum())
        steps = max(index - anchor.index, 1)
        relative = invert_pose(anchor.pose) @ kf.pose
        s.velocity = np.eye(4)
        s.velocity[:3, :3] = cv2.Rodrigues(cv2.Rodrigues(relative[:3, :3])[0] / steps)[0]
        s.velocity[:3, 3] = relative[:3, 3] / steps
        event = {"type": "relocalized", "frame": index, "method": "reinitialized", "place": anchor.index,
                 "inliers": len(two.points), "model": attempt.model, "scale_from": "shared points" if shared
                 else "scene depth", "shared_points": shared,
                 "lost_frames": index - (s.lost_since if s.lost_since is not None else index)}
        s.status, s.lost_since = "tracking", None
        joined = join_maps(s, self.parts, index, kf, K) if s.join is not None else []  # the old map's last places
        return TrackingResult(kf.pose, tracked=True, keyframe_hint=True, depth=sparse_depth(s, kf, camera),
                              events=[event, *joined], quality=1.0)

    # ---- snapshots -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything to continue after a restart (msgpack-able; bounded by the window and the place memory)."""
        return {"version": STATE_VERSION, "config": self.config.model_dump(), **self.state.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from `state_dict()` (the configuration comes with the state)."""
        if int(state.get("version", -1)) != STATE_VERSION:
            raise ValueError(f"visual odometry state version {state.get('version')!r}, expected {STATE_VERSION}")
        self.__init__(VisualOdometryConfig(**state["config"]))
        self.state.load_state_dict(state)
