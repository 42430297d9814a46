"""Visual odometry's initialisation: corners followed until a waiting frame and the current one make a two-view
map (`two_view`); the frames waiting meanwhile hold the position and take the orientation a homography measures,
and are posed on the map once it is made (scaled to a median depth of one, or the old map's after a loss)."""

from __future__ import annotations

import cv2
import numpy as np

from worker.events import Initialized, Initializing
from worker.geometry import Intrinsics

from .base import TrackingResult
from .covisibility import LocalWindow
from .features import Features
from .local_map import Keyframe, LocalMap
from .pose_optimization import optimize_pose
from .projection import camera_matrix, invert_pose, rigid
from .tracks import Tracks, lookup_sorted
from .two_view import TwoViewAttempt, TwoViewMap, two_view_from_matches
from .vo_calibration import freeze_focal, measure_focal
from .vo_mapping import adjust, median_depth, move_map, new_keyframe, sparse_depth
from .vo_state import VoParts, VoState
from .vo_tracks import flow, replenish


def initialise(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics, uncalibrated: bool
              ) -> TrackingResult:
    """Follow corners until a waiting frame (the reference) and this one make a two-view map; new corners join
    at every frame, and the reference is the oldest waiting frame that still shares enough tracks (the waiting
    frames before it are posed too when the map is made). While waiting, a frame holds the position and takes
    the orientation the homography measures (a rotation without parallax is followed, not triangulated)."""
    c = parts.config
    if s.pending:
        uv, ok = flow(s, parts, gray, None)
        s.tracks = Tracks(s.tracks.ids[ok], uv[ok], s.tracks.rows[ok])
    s.previous_gray = gray
    shared = [int(np.isin(s.tracks.ids, ids, assume_unique=True).sum()) for _, ids, _ in s.pending]
    usable = [n for n, count in enumerate(shared) if count >= c.init_min_matches]
    if not usable:  # the view has moved on: wait from this frame
        replenish(s, parts, gray)
        s.pending = [(index, s.tracks.ids.copy(), s.tracks.uv.copy())]
        s.pending_orientation = {index: s.pose[:3, :3].copy()}
        return waiting(s, index, s.pose[:3, :3], "waiting_for_matches", "too few shared tracks")
    reference = usable[0]
    ref_index, ref_ids, ref_uv = s.pending[reference]
    at, found = lookup_sorted(ref_ids, s.tracks.ids)
    common = np.flatnonzero(found)
    if uncalibrated:
        camera = measure_focal(s, ref_uv[at[common]], s.tracks.uv[common], camera)
    K = camera_matrix(camera)
    ones = np.ones(len(common))
    attempt = two_view_from_matches(ref_uv[at[common]], s.tracks.uv[common], K, c, ones, ones,
                                    common, common)
    reference_orientation = s.pending_orientation.get(ref_index, np.eye(3))
    if attempt.map is None:
        orientation = s.pose[:3, :3]
        if attempt.model == "homography" and attempt.rotation is not None:
            orientation = reference_orientation @ attempt.rotation
        replenish(s, parts, gray)
        s.pending = (s.pending + [(index, s.tracks.ids.copy(), s.tracks.uv.copy())]
                     )[-c.init_max_frames:]
        s.pending_orientation[index] = orientation.copy()
        kept = {i for i, _, _ in s.pending}
        s.pending_orientation = {i: r for i, r in s.pending_orientation.items() if i in kept}
        state = "rotation_only" if attempt.rotation_only else "waiting_for_parallax"
        return waiting(s, index, orientation, state, attempt.reason, attempt.model, attempt.score_ratio)
    freeze_focal(s)
    s.pending.append((index, s.tracks.ids.copy(), s.tracks.uv.copy()))
    return start_map(s, parts, index, gray, attempt, reference, camera, uncalibrated, reference_orientation)


def waiting(s: VoState, index: int, orientation: np.ndarray, state: str, reason: str, model: str = "",
            score_ratio: float = 0.0) -> TrackingResult:
    """A frame while the map waits to be made: the held position, the measured orientation, quality 0 (a
    placeholder the `initialized` event revises); an `initializing` event when the waiting state changes."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = orientation, s.pose[:3, 3]
    events = []
    if state != s.init_state:
        s.init_state = state
        events.append(Initializing(frame=index, state=state, reason=reason, model=model,
                                   score_ratio=round(float(score_ratio), 3)))
    if s.maps_started > 1:  # after a loss the frame has no pose: the last one is held, and said so
        return TrackingResult(s.pose.copy(), tracked=False, keyframe_hint=False, events=events, quality=0.0)
    # before the first map the pose is a placeholder the world starts from (the `initialized` event revises it)
    return TrackingResult(rigid(pose), tracked=True, keyframe_hint=False, events=events, quality=0.0)


def start_map(s: VoState, parts: VoParts, index: int, gray: np.ndarray, attempt: TwoViewAttempt, reference: int,
              camera: Intrinsics, uncalibrated: bool, reference_orientation: np.ndarray) -> TrackingResult:
    """The map of a successful two-view attempt (two.ia, two.ib: rows of the current tracks) between the
    waiting frame `reference` and this one: two keyframes, adjusted and scaled; the other waiting frames are
    posed against it. The world keeps the orientation the reference was given while waiting."""
    two = attempt.map
    K = camera_matrix(camera)
    ref_index, ref_ids, ref_uv = s.pending[reference]
    kf_b = two_keyframe_map(s, parts, index, gray, two, ref_index, ref_ids, ref_uv)
    adjust(s, parts, K, LocalWindow(np.array([1]), np.array([0])))
    normalise_scale(s)
    world = np.eye(4)
    world[:3, :3], world[:3, 3] = reference_orientation, s.map_origin[:3, 3]
    move_map(s, world, s.map_depth)
    pose = kf_b.pose
    between, previous = [], world
    for n, (i, ids, uv) in enumerate(s.pending[:-1]):
        fraction = (n - reference) / (len(s.pending) - 1 - reference)
        previous = world if n == reference else pose_between(s, parts, ids, uv, fraction, world, pose, K)
        between.append([i, previous.tolist()])
    s.pending, s.pending_orientation, s.init_state = [], {}, ""
    s.velocity = invert_pose(previous) @ pose
    s.velocity_at = index
    s.status = "tracking"
    # After a loss the waiting frames were reported lost; the new map poses them now (`map` > 1: the engine
    # ties them to this map's first keyframe, so that they move with it when the maps are joined).
    event = Initialized(frame=index, frames=between, map=s.maps_started, points=len(s.map),
                        parallax_deg=round(two.parallax_deg, 3), model=attempt.model,
                        score_ratio=round(attempt.score_ratio, 3),
                        intrinsics=camera.to_dict() if uncalibrated else None)
    return TrackingResult(pose, tracked=True, keyframe_hint=True, depth=sparse_depth(s, kf_b, camera),
                          events=[event], quality=1.0)


def two_keyframe_map(s: VoState, parts: VoParts, index: int, gray: np.ndarray, two: TwoViewMap, ref_index: int,
                     ref_ids: np.ndarray, ref_uv: np.ndarray) -> Keyframe:
    """A new local map of the two-view points, the reference keyframe (at the origin) and this frame's."""
    m = s.map = LocalMap()
    rows = m.add_points(two.points, np.zeros((len(two.points), 32), np.uint8))
    s.tracks.rows[:] = -1
    s.tracks.rows[two.ib] = rows
    # The reference keyframe keeps the tracks it shares with this frame; its image is gone, so it has no
    # descriptors (it is no place to relocalise from).
    at, found = lookup_sorted(ref_ids, s.tracks.ids)
    ref_features = Features(ref_uv[at[found]], np.zeros((int(found.sum()), 32), np.uint8),
                            np.zeros(int(found.sum()), np.int32))
    kf_a = Keyframe(ref_index, np.eye(4), ref_features, s.tracks.rows[found].copy(),
                    s.tracks.ids[found].copy())
    m.keyframes = [kf_a]
    return new_keyframe(s, parts, index, two.pose_b, gray)


def normalise_scale(s: VoState) -> None:
    """Scale the map about the first keyframe so that its median point depth is 1."""
    first = s.map.keyframes[0]
    factor = 1.0 / max(median_depth(s, first), 1e-9)
    m, origin = s.map, first.pose[:3, 3].copy()
    m.positions = origin + factor * (m.positions - origin)
    for kf in m.keyframes:
        kf.pose = kf.pose.copy()
        kf.pose[:3, 3] = origin + factor * (kf.pose[:3, 3] - origin)


def pose_between(s: VoState, parts: VoParts, ids: np.ndarray, uv: np.ndarray, fraction: float, pose_a: np.ndarray,
                 pose_b: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pose of a frame between the two initial views from its tracks of map points (guess: interpolated)."""
    relative = invert_pose(pose_a) @ pose_b
    rotvec = cv2.Rodrigues(relative[:3, :3])[0].ravel() * fraction
    step = np.eye(4)
    step[:3, :3], step[:3, 3] = cv2.Rodrigues(rotvec)[0], relative[:3, 3] * fraction
    guess = pose_a @ step
    order = np.argsort(s.tracks.ids)
    at, found = lookup_sorted(s.tracks.ids[order], ids)
    rows = np.where(found, s.tracks.rows[order][at], -1)
    has = rows >= 0
    if has.sum() < parts.config.min_tracked:
        return guess
    pose, inlier = optimize_pose(guess, s.map.positions[rows[has]], uv[has].astype(np.float64),
                                 np.ones(int(has.sum())), K, parts.config.chi2_px)
    return pose if inlier.sum() >= parts.config.min_tracked and np.all(np.isfinite(pose)) else guess
