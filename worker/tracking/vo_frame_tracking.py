"""Visual odometry's tracking of a frame on the local map: the tracks followed by optical flow (guided by the
motion model) and refined against the last keyframe's image, the pose from those on map points (robust refinement,
PnP + RANSAC when it fails), a keyframe when the tracks drop or the baseline grows. Where too few map points are
found, a turn is followed by the rotation the tracks agree on (`rotation_only`), else by aligning the whole image
(`direct_rotation`); only then is the frame lost (`vo_recovery`)."""

from __future__ import annotations

import cv2
import numpy as np

from worker.events import RotationOnly
from worker.geometry import Intrinsics

from .base import TrackingResult
from .direct_rotation import DirectSettings, align_rotation
from .map_join import moved_points, moved_pose
from .optical_flow import predicted_pixels, refine_points
from .pose_optimization import optimize_pose
from .projection import camera_matrix, invert_pose, rigid, to_camera
from .rotation_only import angular_errors, bearings, fit_rotation, position_given_rotation
from .tracks import Tracks, lookup_sorted
from .vo_map_join import join_maps
from .vo_mapping import insert_keyframe, median_depth, needs_keyframe, sparse_depth, turn_keyframe
from .vo_state import VoParts, VoState
from .vo_tracks import flow


def track_frame(s: VoState, parts: VoParts, index: int, gray: np.ndarray, camera: Intrinsics,
                motion_guess: np.ndarray | None = None) -> TrackingResult | str:
    """The frame tracked on the map (by its tracks, else by the turn they agree on, else by aligning the whole
    image), or why it cannot be: the frame is then lost."""
    c = parts.config
    K = camera_matrix(camera)
    predicted = rigid(s.pose @ (s.velocity if motion_guess is None else motion_guess))
    mapped_before = int(s.tracks.mapped.sum())
    found = follow(s, parts, gray, predicted, K)
    if found is None or found[2] < max(c.min_tracked, c.min_survival * mapped_before):
        s.parallax_seen = False
        turned = follow_rotation(s, parts, index, gray, K, predicted) if c.rotation_bridge else None
        if turned is not None:
            return turned
        aligned = ""
        if c.direct_fallback:
            aligned = ("the tracks show translation adding up, not a turn" if s.parallax_seen
                       else follow_direct(s, parts, index, gray, K, predicted))
        if isinstance(aligned, TrackingResult):
            return aligned
        refused = f"; image alignment: {aligned}" if aligned else ""
        if found is None:
            return f"too few map points tracked (sudden motion, occlusion or a new view){refused}"
        return f"{found[2]} of {mapped_before} tracked points found again (a sudden change){refused}"
    pose, tracks, inliers = found
    s.rotation_since = s.direct_since = None
    s.tracks, s.previous_gray = tracks, gray
    s.velocity, s.velocity_at = rigid(invert_pose(s.pose) @ pose), index
    s.frames_since_keyframe += 1
    quality = min(1.0, inliers / max(s.tracked_at_keyframe, 1))
    if not needs_keyframe(s, parts, pose, inliers):
        return TrackingResult(pose, tracked=True, keyframe_hint=False, quality=quality)
    kf = insert_keyframe(s, parts, index, pose, gray, K)
    s.velocity = rigid(s.velocity @ invert_pose(pose) @ kf.pose)
    events = join_maps(s, parts, index, kf, K) if s.join is not None else []
    if covered(s, parts, index, kf.pose, K, camera):
        return TrackingResult(kf.pose, tracked=True, keyframe_hint=False, quality=quality, events=events)
    return TrackingResult(kf.pose, tracked=True, keyframe_hint=True, depth=sparse_depth(s, kf, camera),
                          quality=quality, events=events)


def covered(s: VoState, parts: VoParts, index: int, pose: np.ndarray, K: np.ndarray, camera: Intrinsics) -> bool:
    """Whether an engine keyframe at least `reuse_min_age` frames old lies near `pose` and sees at least
    `reuse_overlap` of the frame's tracked map points (in its image, in front of it)."""
    c = parts.config
    t = s.tracks
    points = s.map.positions[t.rows[t.mapped]]
    if c.reuse_keyframes <= 0 or len(points) < c.min_tracked:
        return False
    pose, points = moved_pose(s.output, pose), moved_points(s.output, points)  # the engine's poses
    depth = to_camera(points, pose)[:, 2]
    median = float(np.median(depth[depth > 0])) if np.any(depth > 0) else 1.0
    for kf_index, kf_pose in s.engine_keyframes:
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


def follow(s: VoState, parts: VoParts, gray: np.ndarray, predicted: np.ndarray, K: np.ndarray
           ) -> tuple[np.ndarray, Tracks, int] | None:
    """The tracks carried from the last tracked frame into `gray`, less the pose's outliers, the pose and its
    inlier count (None: too few); nothing is changed."""
    t = s.tracks
    guess = predicted_pixels(t.uv, s.map.positions[t.rows[t.mapped]], t.mapped, s.pose, predicted, K)
    uv, ok = flow(s, parts, gray, guess)
    if (ok & t.mapped).sum() < 0.5 * t.mapped.sum():  # a wrong guess can mislead the flow: try none
        uv_plain, ok_plain = flow(s, parts, gray, None)
        if (ok_plain & t.mapped).sum() > (ok & t.mapped).sum():
            uv, ok = uv_plain, ok_plain
    tracks = refine_on_keyframe(s, parts, Tracks(t.ids[ok], uv[ok], t.rows[ok]), gray, predicted)
    found = pose_from_tracks(s, parts, tracks, predicted, K)
    if found is None:
        return None
    pose, inlier = found
    keep = np.ones(len(tracks), bool)
    keep[np.flatnonzero(tracks.mapped)[~inlier]] = False
    return pose, tracks.subset(keep), int(inlier.sum())


def follow_rotation(s: VoState, parts: VoParts, index: int, gray: np.ndarray, K: np.ndarray, predicted: np.ndarray
                    ) -> TrackingResult | None:
    """Track a frame whose map points are too few by the rotation every track agrees on (`rotation_only`):
    the position comes from the map points still tracked, or is held; None when the tracks do not agree on a
    rotation (parallax, a bad frame). Its tracks carry on; VO keyframes (not offered to the engine: a turn
    gives multi-view stereo no baseline) keep new tracks coming, so that points are triangulated again once
    the camera moves."""
    c, t = parts.config, s.tracks
    guess = predicted_pixels(t.uv, s.map.positions[t.rows[t.mapped]], t.mapped, s.pose, predicted, K)
    uv, ok = flow(s, parts, gray, guess)
    if ok.sum() < c.rotation_min_tracks:
        return None
    followed = np.flatnonzero(ok)
    tolerance = c.rotation_tolerance_px / K[0, 0]
    fit = fit_rotation(bearings(t.uv[followed], K), bearings(uv[followed], K), tolerance)
    if fit is None or fit[1].sum() < max(c.rotation_min_tracks, c.rotation_min_share * len(followed)):
        return None
    turn, agree = fit  # previous camera -> this camera
    orientation = s.pose[:3, :3] @ turn.T
    keep = np.zeros(len(t), bool)
    keep[followed[agree]] = True
    position, measured = s.pose[:3, 3].copy(), 0
    mapped = followed[t.mapped[followed]]
    if len(mapped) >= c.rotation_position_points:
        found = position_given_rotation(orientation, s.map.positions[t.rows[mapped]], bearings(uv[mapped], K),
                                        2.0 * tolerance)
        depth = median_depth(s, s.map.keyframes[-1]) if s.map.keyframes else s.map_depth
        if (found is not None and found[1].sum() >= c.rotation_position_points
                and np.linalg.norm(found[0] - position) <= c.rotation_max_step * depth):
            position, measured = found[0], int(found[1].sum())
            keep[mapped] = found[1]
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = orientation, position
    pose = rigid(pose)
    tracks = Tracks(t.ids[keep], uv[keep], t.rows[keep])
    if s.rotation_since is not None and not still_a_turn(s, parts, tracks, pose, K, tolerance):
        s.parallax_seen = True  # translation adds up: no turn model may place this frame
        return None
    s.tracks = tracks
    s.previous_gray = gray
    s.velocity, s.velocity_at = rigid(invert_pose(s.pose) @ pose), index
    s.frames_since_keyframe += 1
    s.direct_since = None  # the tracks measure the turn again: a run of aligned frames ends
    turn_keyframe(s, parts, index, pose, gray, K, run_began=s.rotation_since is not None)
    events = []
    if s.rotation_since is None:
        s.rotation_since = index
        events.append(RotationOnly(frame=index, tracks=int(agree.sum()), map_points=measured))
    return TrackingResult(pose, tracked=True, keyframe_hint=False, events=events,
                          quality=0.5 * float(agree.mean()), translation_measured=measured > 0)


def follow_direct(s: VoState, parts: VoParts, index: int, gray: np.ndarray, K: np.ndarray, predicted: np.ndarray
                  ) -> TrackingResult | str:
    """Track a frame the tracks cannot place (stripes, a plain wall, blur) by aligning its whole image to the
    last tracked frame's (`direct_rotation`): the turn measured where the image constrains it and predicted
    where it does not, the position from the constant-velocity motion; why not when the fit is poor or the
    image measures nothing (the frame is then lost). The tracks the flow follows carry on, and VO keyframes (not
    offered to the engine) start new ones, so that points are triangulated on the poses of the run and feature
    tracking takes over again as soon as they measure enough of them."""
    c, t = parts.config, s.tracks
    if s.previous_gray is None:
        return "no previous image"
    if s.velocity_at != s.last_tracked:  # just relocalised or restarted: the motion model is a guess
        return "no measured motion to predict the move from"
    if s.direct_since is not None and index - s.direct_since >= c.direct_max_frames:
        return f"the run of aligned frames reached {c.direct_max_frames}"
    step = invert_pose(s.pose) @ predicted  # the predicted motion, previous camera -> this one
    prior = step[:3, :3].T
    if s.direct_since is None:  # the scene depth where the run begins (its keyframes have few points)
        s.direct_depth = scene_depth(s, parts)
    depth = s.direct_depth
    baseline = float(np.linalg.norm(step[:3, 3])) / max(depth, 1e-9)
    if baseline > c.direct_max_baseline:
        return f"the predicted move is {baseline:.3f} of the scene depth (> {c.direct_max_baseline}): not a turn"
    settings = DirectSettings(prior_deg=c.direct_prior_deg, min_correlation=c.direct_min_correlation,
                              max_axis_sigma_deg=c.direct_max_axis_sigma_deg,
                              max_correction_deg=c.direct_max_correction_deg)
    fit = align_rotation(s.previous_gray, gray, K, prior, -prior @ step[:3, 3], depth, settings=settings)
    held = fit.accepted
    if not held and c.direct_translation_sigma > 0:
        # the predicted move may be wrong (it came from the frames before the tracks failed): let the centre
        # move too, as a nuisance of the fit, and keep only the turn (the image's move assumes a plane)
        fit = align_rotation(s.previous_gray, gray, K, prior, -prior @ step[:3, 3], depth,
                             c.direct_translation_sigma * depth, settings)
    if not fit.accepted:
        return fit.reason
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = fit.rotation.T, step[:3, 3]  # the turn measured, the centre predicted
    pose = rigid(s.pose @ motion)
    guess = predicted_pixels(t.uv, s.map.positions[t.rows[t.mapped]], t.mapped, s.pose, pose, K)
    uv, ok = flow(s, parts, gray, guess)
    ok[t.mapped] &= np.linalg.norm(uv[t.mapped] - guess[t.mapped], axis=1) <= c.direct_track_tolerance_px
    s.tracks = Tracks(t.ids[ok], uv[ok], t.rows[ok])
    s.previous_gray = gray
    s.velocity, s.velocity_at = rigid(invert_pose(s.pose) @ pose), index
    s.frames_since_keyframe += 1
    s.rotation_since = None
    turn_keyframe(s, parts, index, pose, gray, K, run_began=s.direct_since is not None)
    events = []
    if s.direct_since is None:
        s.direct_since = index
        events.append(RotationOnly(frame=index, method="photometric", tracks=0, map_points=0,
                                   correlation=round(fit.correlation, 3), measured_axes=fit.measured_axes))
    return TrackingResult(pose, tracked=True, keyframe_hint=False, events=events,
                          quality=(0.4 if held else 0.2) * max(fit.correlation, 0.0), translation_measured=False)


def scene_depth(s: VoState, parts: VoParts) -> float:
    """Median depth of the map points the last frame's tracks measure; else the newest keyframe's with points;
    else the map's."""
    t = s.tracks
    if t.mapped.sum() >= parts.config.min_tracked:
        depth = to_camera(s.map.positions[t.rows[t.mapped]], s.pose)[:, 2]
        if (depth > 0).sum() >= parts.config.min_tracked:
            return float(np.median(depth[depth > 0]))
    for kf in reversed(s.map.keyframes):
        if (kf.point_ids >= 0).sum() >= parts.config.min_tracked:
            return median_depth(s, kf)
    return s.map_depth


def still_a_turn(s: VoState, parts: VoParts, tracks: Tracks, pose: np.ndarray, K: np.ndarray, tolerance: float) -> bool:
    """Whether the tracks shared with the last keyframe (made in this rotation-only run) still agree with a
    turn about one centre: translation that adds up over frames shows as parallax against it."""
    kf = s.map.keyframes[-1]
    order = np.argsort(kf.track_ids)
    at, found = lookup_sorted(kf.track_ids[order], tracks.ids)
    if found.sum() < parts.config.rotation_min_tracks:
        return True  # too few shared tracks to tell: the frame-to-frame fit decides
    then = bearings(kf.features.keypoints[order[at[found]]], K)
    turn = pose[:3, :3].T @ kf.pose[:3, :3]  # keyframe camera -> this camera
    agree = angular_errors(then, bearings(tracks.uv[found], K), turn) < 2.0 * tolerance
    return bool(agree.mean() >= parts.config.rotation_min_share)


def refine_on_keyframe(s: VoState, parts: VoParts, tracks: Tracks, gray: np.ndarray, predicted: np.ndarray) -> Tracks:
    """The tracks that began at or before the last keyframe, matched against that keyframe's image where their
    image scale has not changed much since (the match is a shift, not a zoom; moving forward zooms)."""
    c = parts.config
    if s.keyframe_gray is None or not c.flow_refine_px or not s.map.keyframes:
        return tracks
    kf = s.map.keyframes[-1]
    order = np.argsort(kf.track_ids)
    at, found = lookup_sorted(kf.track_ids[order], tracks.ids)
    zoom = np.ones(len(tracks))
    mapped = tracks.mapped
    if mapped.any():
        points = s.map.positions[tracks.rows[mapped]]
        then, now = to_camera(points, kf.pose)[:, 2], to_camera(points, predicted)[:, 2]
        zoom[mapped] = then / np.maximum(now, 1e-9)
        zoom[~mapped] = np.median(zoom[mapped])
    found &= np.abs(zoom - 1.0) <= c.flow_refine_zoom
    uv = tracks.uv.copy()
    uv[found] = refine_points(s.keyframe_gray, gray, kf.features.keypoints[order[at[found]]], uv[found],
                              window=c.flow_window, max_shift_px=c.flow_refine_px)
    return Tracks(tracks.ids, uv, tracks.rows)


def pose_from_tracks(s: VoState, parts: VoParts, tracks: Tracks, guess: np.ndarray, K: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose from the tracks of map points (robust refinement, PnP + RANSAC when it fails) and the inlier mask
    over those tracks, or None."""
    c = parts.config
    mapped = np.flatnonzero(tracks.mapped)
    if len(mapped) < c.min_tracked:
        return None
    points = s.map.positions[tracks.rows[mapped]]
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
