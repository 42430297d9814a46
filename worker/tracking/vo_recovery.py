"""Visual odometry losing the map and finding the way back: a lost frame keeps the last tracked frame as the anchor;
the next frames try the anchor's tracks again (a short loss), ORB place recognition over the remembered keyframes,
a map restarted from two views between the anchor and the frame (scaled by the old points the two share), XFeat
against the anchor and the remembered keyframes (`learned_places`), and at last a new map of its own
(`vo_initialisation`), joined to the old one later (`vo_map_join`)."""

from __future__ import annotations

import cv2
import numpy as np

from worker.events import NewMap, Relocalized, TrackingLost
from worker.geometry import Intrinsics

from .base import TrackingResult
from .covisibility import LocalWindow
from .local_map import LocalMap
from .optical_flow import predicted_pixels
from .pose_optimization import pnp_pose
from .projection import camera_matrix, invert_pose, rigid
from .tracks import Tracks, lookup_sorted
from .two_view import two_view_from_matches
from .vo_frame_tracking import follow
from .vo_initialisation import initialise, two_keyframe_map
from .vo_map_join import join_maps
from .vo_mapping import adjust, median_depth, move_map, new_keyframe, sparse_depth
from .vo_places import learned_candidates, orb_features, place_of, retire
from .vo_state import Anchor, JoinState, VoParts, VoState
from .vo_tracks import flow, replenish
from .xfeat import XFeatures, mutual_matches


def lose_or_restart(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics, reason: str
                   ) -> TrackingResult:
    """Lose tracking; when a map restarts from the last tracked frame at once, this frame is tracked on it
    (both events are reported: the old map's tracks broke here)."""
    lost = lose(s, parts, index, reason)
    restarted = reinitialise(s, parts, index, gray, camera) or relocalise_learned(s, parts, index, gray, camera)
    if restarted is None:
        return lost
    restarted.events = lost.events + restarted.events
    return restarted


def lose(s: VoState, parts: VoParts, index: int, reason: str) -> TrackingResult:
    """Tracking is lost: the held pose, and the last tracked frame kept as the anchor a map may restart from
    (when the loss breaks tracking, not a restart or an initialisation)."""
    was_tracking = s.status == "tracking"
    if was_tracking:
        s.mapped_at_loss = int(s.tracks.mapped.sum())
    s.status = "lost"
    s.lost_since, s.rotation_since, s.direct_since = index, None, None
    s.anchor = None
    if parts.config.reinit_after_loss and s.previous_gray is not None and was_tracking:
        replenish(s, parts, s.previous_gray)  # the anchor's corners, not only its surviving tracks
        t = s.tracks
        points = np.full((len(t), 3), np.nan)
        points[t.mapped] = s.map.positions[t.rows[t.mapped]]
        s.anchor = Anchor(s.last_tracked, s.pose.copy(), t.ids.copy(), t.uv.copy(), points,
                          s.velocity.copy(), s.pose.copy(), s.previous_gray)
    s.velocity = np.eye(4)
    return TrackingResult(s.pose.copy(), tracked=False, keyframe_hint=False, quality=0.0,
                          events=[TrackingLost(reason=reason, frame=index)])


def relocalise(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult:
    """Back on track when most tracks of the last tracked frame are found again in this one (a short loss:
    bad frames, an occlusion); else place recognition over the remembered keyframes, where a hit starts a new
    local map from the place's points seen in this frame (their positions, hence the scale, carry over)."""
    c = parts.config
    K = camera_matrix(camera)
    found = follow(s, parts, gray, s.pose, K)
    # Measured against the tracks at the loss: those followed through the lost frames are fewer.
    if found is not None and found[2] >= c.recover_share * max(s.mapped_at_loss, s.tracks.mapped.sum()):
        pose, s.tracks, inliers = found
        s.previous_gray = gray
        event = Relocalized(frame=index, place=s.map.keyframes[-1].index, inliers=inliers,
                            lost_frames=index - (s.lost_since if s.lost_since is not None else index))
        s.status, s.lost_since, s.velocity, s.anchor = "tracking", None, np.eye(4), None
        return TrackingResult(pose, tracked=True, keyframe_hint=False, events=[event],
                              quality=min(1.0, inliers / max(s.tracked_at_keyframe, 1)))
    recognised = recognise_place(s, parts, index, gray, camera)
    if recognised is not None:
        return recognised
    restarted = reinitialise(s, parts, index, gray, camera) or relocalise_learned(s, parts, index, gray, camera)
    if restarted is not None:
        return restarted
    lost_for = index - (s.lost_since if s.lost_since is not None else index)
    if c.new_map_after_lost and lost_for >= c.new_map_after_lost and textured(s, parts, index, gray):
        return begin_new_map(s, parts, index, gray, camera, lost_for)
    return TrackingResult(s.pose.copy(), tracked=False, keyframe_hint=False, quality=0.0)


def recognise_place(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics
                   ) -> TrackingResult | None:
    """Place recognition over the remembered keyframes (ORB, verified by PnP): a hit starts a new local map
    from the place's points seen in this frame (their positions, hence the scale, carry over); None: no hit."""
    features = orb_features(s, parts, index, gray)
    if len(features) < parts.config.min_features:
        return None
    places = s.retired + [place_of(s, parts, kf) for kf in s.map.keyframes]
    hit = parts.recognizer.relocalise(features, places, camera_matrix(camera),
                                      parts.extractor.level_sigmas(features.octaves))
    if hit is None:
        return None
    return restart_from(s, parts, index, gray, camera, hit.pose, features.keypoints[hit.keypoints], hit.points,
                        hit.place, "place recognition")


def textured(s: VoState, parts: VoParts, index: int, gray: np.ndarray) -> bool:
    """Whether the frame has the features an initialisation needs, and at least 30 % of the last keyframe's (a
    covered lens or a blurred frame begins no map)."""
    keyframes = s.map.keyframes
    usual = len(keyframes[-1].features.keypoints) if keyframes else 0
    return len(orb_features(s, parts, index, gray)) >= max(parts.config.init_min_matches, 0.3 * usual)


def begin_new_map(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics, lost_for: int
                 ) -> TrackingResult:
    """Give up finding the old map from here: its keyframes become places, and a new map initialises from
    this frame on, placed at the last pose with the old map's median scene depth (a guess: the two share no
    point) until a loop or relocalisation joins them. A `new_map` event says so."""
    depth = median_depth(s, s.map.keyframes[-1]) if s.map.keyframes else s.map_depth
    retire(s, parts, s.map.keyframes)
    s.map, s.tracks, s.anchor = LocalMap(), Tracks.empty(), None
    s.pending, s.pending_orientation, s.init_state = [], {}, ""
    s.previous_gray = s.keyframe_gray = None
    s.velocity = np.eye(4)
    s.frames_since_keyframe = s.tracked_at_keyframe = 0
    s.map_origin, s.map_depth = s.pose.copy(), depth
    s.maps_started += 1
    if parts.config.join_maps:  # joined to an older map once one of its keyframes recognises an older place
        s.map_id, s.maps_made, s.join = s.maps_made, s.maps_made + 1, JoinState(index)
    s.status, s.lost_since = "initializing", None
    result = initialise(s, parts, index, gray, camera, uncalibrated=False)
    result.events = [NewMap(frame=index, map=s.maps_started, lost_frames=lost_for, scene_depth=round(depth, 4)),
                     *result.events]
    return result


def restart_from(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics, pose: np.ndarray,
                 uv: np.ndarray, points: np.ndarray, place: int, method: str) -> TrackingResult:
    """A new local map from the old map's points (world [n, 3]) seen at pixels uv [n, 2] of this frame, posed
    at `pose` (their positions, hence the scale, carry over); the old keyframes become places."""
    s.anchor = None
    retire(s, parts, s.map.keyframes)
    place_map = next((p.map_id for p in s.retired if p.index == place), s.map_id)
    if place_map != s.map_id:  # back in an older map's frame: its points carry that map's coordinates
        s.map_id, s.join = place_map, None
    m = s.map = LocalMap()
    rows = m.add_points(points, np.zeros((len(points), 32), np.uint8))
    ids = np.arange(s.next_id, s.next_id + len(rows), dtype=np.int64)
    s.next_id += len(rows)
    s.tracks = Tracks(ids, np.asarray(uv, np.float32).reshape(-1, 2), rows)
    kf = new_keyframe(s, parts, index, pose, gray)
    s.tracked_at_keyframe = len(rows)
    s.previous_gray = gray
    event = Relocalized(frame=index, place=place, inliers=len(rows), method=method,
                        lost_frames=index - (s.lost_since if s.lost_since is not None else index))
    s.status, s.lost_since, s.velocity = "tracking", None, np.eye(4)
    return TrackingResult(pose, tracked=True, keyframe_hint=True, depth=sparse_depth(s, kf, camera),
                          events=[event], quality=1.0)


def relocalise_learned(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics
                      ) -> TrackingResult | None:
    """XFeat matching of this frame to the anchor's map points (the last tracked frame) and then to remembered
    keyframes (`vo_places.learned_candidates`), each verified by PnP + RANSAC and the robust refinement: the old map,
    hence its scale, carries on past a turn too fast for optical flow and ORB (None: not found). Runs on every
    `learned_reloc_every`-th lost frame, the first one included, within the frame's network passes
    (`learned_passes_per_frame`: what is not described yet waits for the next try)."""
    c = parts.config
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
            anchor.descriptors, anchor.world = learned_place(parts, anchor)
        current = parts.learned.of_frame(index, gray)
        if current is not None and len(anchor.world) >= c.reloc_min_inliers:
            ia, ib = mutual_matches(anchor.descriptors, current.descriptors, c.learned_min_similarity)
            if len(ia) >= c.reloc_min_inliers:
                X, uv = anchor.world[ia], current.keypoints[ib].astype(np.float64)
                found = pnp_pose(X, uv, K, np.full(len(X), 2.0), c.chi2_px, c.reloc_min_inliers)
                if found is not None:
                    pose, inlier = found
                    return restart_from(s, parts, index, gray, camera, pose, uv[inlier], X[inlier], anchor.index,
                                        "learned")
    candidates = learned_candidates(s, parts, index, gray)
    if not candidates:
        return None
    current = parts.learned.of_frame(index, gray, orb_features(s, parts, index, gray).keypoints)
    if current is None:
        return None
    hit = parts.learned.relocalise(current, candidates, K, c.learned_keyframe_min_inliers)
    if hit is not None:
        return restart_from(s, parts, index, gray, camera, hit.pose, current.keypoints[hit.keypoints], hit.points,
                            hit.place, "learned keyframe")
    # Wide baselines: LighterGlue on every candidate, also those the pass budget left undescribed this frame (a
    # jump's lost frames may be few: the fox's are, before a new map begins).
    glue = c.learned_glue and parts.learned.glue_due(index, c.learned_glue_every)
    glued = parts.learned.glue_relocalise(gray, candidates, K, c.learned_keyframe_min_inliers) if glue else None
    if glued is None:
        return None
    hit, uv = glued
    return restart_from(s, parts, index, gray, camera, hit.pose, uv[hit.keypoints], hit.points, hit.place,
                        "learned glue")


def learned_place(parts: VoParts, anchor: Anchor) -> tuple[np.ndarray, np.ndarray]:
    """XFeat descriptors [n, 64] of the anchor image's keypoints that lie on one of its tracked map points
    (within `place_radius_px`), and those points [n, 3] (none while the frame has no network pass left)."""
    found = parts.learned.describe_image(anchor.gray)
    anchor.described = found is not None
    has = np.isfinite(anchor.points).all(axis=1)
    if found is None or len(found) == 0 or not has.any():
        return np.zeros((0, 64), np.float32), np.zeros((0, 3))
    d2 = ((found.keypoints[:, None, :] - anchor.uv[None, has, :]) ** 2).sum(-1)
    nearest = d2.argmin(axis=1)
    near = np.flatnonzero(d2[np.arange(len(found)), nearest] <= (2.0 * parts.config.place_radius_px) ** 2)
    return found.descriptors[near], anchor.points[has][nearest[near]]


def reinitialise(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics) -> TrackingResult | None:
    """A new map from a two-view reconstruction between the last tracked frame (the anchor, whose pose is
    known) and this one, placed at the anchor and scaled by the old map points the two share (else by the
    old map's depth at the anchor); None while that fails. The anchor's tracks are followed meanwhile."""
    c = parts.config
    anchor = s.anchor
    if anchor is None:
        return None
    K = camera_matrix(camera)
    t = s.tracks
    predicted = rigid(anchor.predicted @ anchor.velocity)  # the motion model guides the flow while lost
    rows = np.where(t.rows < len(s.map), t.rows, -1)
    mapped = rows >= 0
    guess = predicted_pixels(t.uv, s.map.positions[rows[mapped]], mapped, anchor.predicted, predicted, K)
    uv, ok = flow(s, parts, gray, guess)
    if ok.sum() < 0.5 * len(t):
        uv_plain, ok_plain = flow(s, parts, gray, None)
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
    retire(s, parts, s.map.keyframes)
    if c.join_maps:  # a map of its own until a place of the old one is recognised
        s.map_id, s.maps_made, s.join = s.maps_made, s.maps_made + 1, JoinState(index)
    kf = two_keyframe_map(s, parts, index, gray, two, anchor.index, anchor.ids, anchor.uv)
    adjust(s, parts, K, LocalWindow(np.array([1]), np.array([0])))
    move_map(s, anchor.pose, scale)
    s.anchor = None
    s.tracked_at_keyframe = int(s.tracks.mapped.sum())
    steps = max(index - anchor.index, 1)
    relative = invert_pose(anchor.pose) @ kf.pose
    s.velocity = np.eye(4)
    s.velocity[:3, :3] = cv2.Rodrigues(cv2.Rodrigues(relative[:3, :3])[0] / steps)[0]
    s.velocity[:3, 3] = relative[:3, 3] / steps
    event = Relocalized(frame=index, method="reinitialized", place=anchor.index, inliers=len(two.points),
                        model=attempt.model, scale_from="shared points" if shared else "scene depth",
                        shared_points=shared, lost_frames=index - (s.lost_since if s.lost_since is not None
                                                                   else index))
    s.status, s.lost_since = "tracking", None
    joined = join_maps(s, parts, index, kf, K) if s.join is not None else []  # the old map's last places
    return TrackingResult(kf.pose, tracked=True, keyframe_hint=True, depth=sparse_depth(s, kf, camera),
                          events=[event, *joined], quality=1.0)
