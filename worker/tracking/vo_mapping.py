"""Visual odometry's map: when a frame becomes a keyframe, keyframes with new corners, map points triangulated from
the candidate tracks (`track_triangulation`) and found again by projection (`reobservation`), the window slid and
adjusted (`bundle_adjustment`, over the `covisibility` window), the map moved by a similarity, and the depths the
keyframes see."""

from __future__ import annotations

import numpy as np

from worker.geometry import Intrinsics

from .bundle_adjustment import Observations, bundle_adjust, reprojection_chi2
from .covisibility import LocalWindow, covisible_window
from .features import Features
from .local_map import Keyframe
from .projection import rigid, sparse_depth_image, to_camera
from .reobservation import nearest_keypoints, search_by_projection
from .track_triangulation import triangulate_tracks
from .tracks import Tracks, lookup_sorted
from .vo_places import orb_features, retire
from .vo_state import VoParts, VoState
from .vo_tracks import replenish


def new_keyframe(s: VoState, parts: VoParts, index: int, pose: np.ndarray, gray: np.ndarray) -> Keyframe:
    """A keyframe of every track (after new corners are added), appended to the map."""
    replenish(s, parts, gray)
    t = s.tracks
    features = Features(t.uv.copy(), np.zeros((len(t), 32), np.uint8), np.zeros(len(t), np.int32))
    kf = Keyframe(index, pose.copy(), features, t.rows.copy(), t.ids.copy(), orb_features(s, parts, index, gray))
    s.map.keyframes.append(kf)
    kept = {k.index for k in s.map.keyframes}
    s.keyframe_images = {i: g for i, g in s.keyframe_images.items() if i in kept}
    s.keyframe_images[index] = gray
    s.keyframe_gray = gray
    s.frames_since_keyframe = 0
    return kf


def insert_keyframe(s: VoState, parts: VoParts, index: int, pose: np.ndarray, gray: np.ndarray, K: np.ndarray
                    ) -> Keyframe:
    """A keyframe at this tracked frame: new corners, points triangulated (and found again by projection), the
    window slid (the keyframes leaving it become places) and adjusted."""
    kf = new_keyframe(s, parts, index, pose, gray)
    c = parts.config
    triangulate(s, parts, K, s.map.keyframes[-(c.window + c.fixed_keyframes + 1):])
    if c.reobserve_points:
        reobserve(s, parts, kf, K)
    gone = s.map.slide(c.map_keyframes if c.covisibility_ba else c.window + c.fixed_keyframes)
    retire(s, parts, gone)
    renumber_tracks(s, s.map.forget_unobserved())
    count = len(s.map.keyframes)
    if count >= 3:
        if c.covisibility_ba:
            window = covisible_window([k.point_ids for k in s.map.keyframes], count - 1, c.window,
                                      c.covisible_fixed, min_fixed=c.fixed_keyframes)
        else:
            held = min(max(c.fixed_keyframes, count - c.window), count - 1)
            window = LocalWindow(np.arange(held, count), np.arange(held))
        adjust(s, parts, K, window)
    s.tracked_at_keyframe = int(s.tracks.mapped.sum())
    s.archive.note_handed_out(index, kf.pose)
    return kf


def turn_keyframe(s: VoState, parts: VoParts, index: int, pose: np.ndarray, gray: np.ndarray, K: np.ndarray,
                  run_began: bool) -> None:
    """A keyframe where a turn model placed the frame: at a run's first frame, and again whenever the tracks
    fall below `rotation_keyframe_share` of the last keyframe's (the view has turned on)."""
    c = parts.config
    last = s.map.keyframes[-1] if s.map.keyframes else None
    if run_began and last is not None and len(s.tracks) >= c.rotation_keyframe_share * len(last.track_ids):
        return
    new_keyframe(s, parts, index, pose, gray)
    triangulate(s, parts, K, s.map.keyframes[-(c.window + c.fixed_keyframes + 1):])
    retire(s, parts, s.map.slide(c.map_keyframes if c.covisibility_ba else c.window + c.fixed_keyframes))
    renumber_tracks(s, s.map.forget_unobserved())
    s.tracked_at_keyframe = max(int(s.tracks.mapped.sum()), 1)


def needs_keyframe(s: VoState, parts: VoParts, pose: np.ndarray, tracked: int) -> bool:
    """Whether a frame at `pose` with `tracked` inliers becomes a keyframe: its tracks dropped, the baseline grew,
    or it has been long enough with some baseline."""
    c = parts.config
    if s.frames_since_keyframe < c.keyframe_min_gap:
        return False
    last = s.map.keyframes[-1]
    baseline = np.linalg.norm(pose[:3, 3] - last.pose[:3, 3]) / max(median_depth(s, last), 1e-6)
    weak = tracked < c.keyframe_tracked_ratio * s.tracked_at_keyframe
    stale = s.frames_since_keyframe >= c.keyframe_max_gap and baseline > 0.2 * c.keyframe_baseline
    return weak or stale or baseline > c.keyframe_baseline


def triangulate(s: VoState, parts: VoParts, K: np.ndarray, keyframes: list[Keyframe]) -> None:
    """Map points from the candidate tracks of the newest keyframe seen first by one of `keyframes` (oldest
    first, the newest last; see `triangulate_tracks`)."""
    m, t = s.map, s.tracks
    candidate = t.rows < 0
    new = triangulate_tracks(keyframes, t.ids[candidate], t.uv[candidate], K, parts.config.chi2_px,
                             parts.config.min_parallax_deg)
    rows = m.add_points(new.points, np.zeros((len(new.points), 32), np.uint8))
    for keyframe in m.keyframes:
        at, found = lookup_sorted(new.ids, keyframe.track_ids)
        keyframe.point_ids[found] = rows[at[found]]
    at, found = lookup_sorted(new.ids, t.ids)
    t.rows[found] = rows[at[found]]
    if len(new.inconsistent):
        s.tracks = t.subset(~np.isin(t.ids, new.inconsistent))


def reobserve(s: VoState, parts: VoParts, kf: Keyframe, K: np.ndarray) -> None:
    """Describe the points the tracks measure at the new keyframe `kf` (ORB), then match the described points
    no track follows to its ORB features (`reobservation`): a candidate track on the keypoint takes the point,
    and away from every track a new track starts there; `kf` observes them."""
    c, m, t = parts.config, s.map, s.tracks
    radius = c.place_radius_px * parts.extractor.level_sigmas(kf.orb.octaves)
    mapped = np.flatnonzero(t.mapped)
    bare = mapped[~m.descriptors[t.rows[mapped]].any(axis=1)]
    nearest, near = nearest_keypoints(t.uv[bare].astype(np.float64), kf.orb, radius)
    m.descriptors[t.rows[bare[near]]] = kf.orb.descriptors[nearest[near]]
    followed = np.zeros(len(m), bool)
    followed[t.rows[mapped]] = True
    candidates = np.flatnonzero(~followed & m.descriptors.any(axis=1))
    rows, keypoints = search_by_projection(m.positions, m.descriptors, candidates, kf.pose, K, s.image_size,
                                           kf.orb, c.reobserve_radius_px, c.reobserve_max_hamming, c.match_ratio)
    if len(rows) == 0 or len(t) == 0:
        return
    uv = kf.orb.keypoints[keypoints].astype(np.float32)
    d2 = ((uv[:, None, :] - t.uv[None, :, :]) ** 2).sum(-1)
    closest = d2.argmin(axis=1)
    distance = np.sqrt(d2[np.arange(len(uv)), closest])
    taken = np.flatnonzero((distance <= c.reobserve_snap_px) & (t.rows[closest] < 0))
    take = np.zeros(len(uv), bool)
    take[taken[np.unique(closest[taken], return_index=True)[1]]] = True  # one point per track
    t.rows[closest[take]] = rows[take]
    order = np.argsort(kf.track_ids)
    at, found = lookup_sorted(kf.track_ids[order], t.ids[closest[take]])
    kf.point_ids[order[at[found]]] = rows[take][found]
    fresh = distance > c.corner_min_distance * max(s.image_size)
    if fresh.any():
        ids = np.arange(s.next_id, s.next_id + int(fresh.sum()), dtype=np.int64)
        s.next_id += len(ids)
        s.tracks = Tracks(np.r_[t.ids, ids], np.concatenate([t.uv, uv[fresh]]), np.r_[t.rows, rows[fresh]])
        f = kf.features
        kf.features = Features(np.concatenate([f.keypoints, uv[fresh]]),
                               np.concatenate([f.descriptors, np.zeros((len(ids), 32), np.uint8)]),
                               np.concatenate([f.octaves, np.zeros(len(ids), f.octaves.dtype)]))
        kf.point_ids, kf.track_ids = np.r_[kf.point_ids, rows[fresh]], np.r_[kf.track_ids, ids]


def renumber_tracks(s: VoState, remap: np.ndarray) -> None:
    """Follow the map's renumbering of points in the tracks (a track whose point went becomes a candidate)."""
    s.tracks.rows = remap[s.tracks.rows]


def adjust(s: VoState, parts: VoParts, K: np.ndarray, window: LocalWindow) -> None:
    """Bundle adjustment of the window's free keyframes and the points they observe, its fixed keyframes held;
    observations it finds wrong are dropped (and the tracks they came from when the newest keyframe made
    them), and points nobody sees."""
    m = s.map
    slots = window.slots
    obs = m.observations(parts.extractor.level_sigmas)
    keep = np.isin(obs.keyframe, slots)
    obs = Observations(np.searchsorted(slots, obs.keyframe[keep]), obs.point[keep], obs.uv[keep],
                       obs.sigma[keep])
    if len(obs.point) == 0:
        return
    fixed = ~np.isin(slots, window.free)
    poses = np.stack([m.keyframes[k].pose for k in slots])
    poses, m.positions, _ = bundle_adjust(poses, fixed, m.positions, obs, K, parts.config.ba_iterations,
                                          parts.config.huber_sigmas)
    for slot, pose in zip(slots, poses, strict=True):
        m.keyframes[slot].pose = pose
    bad = reprojection_chi2(poses, m.positions, obs, K) > parts.config.chi2_px
    for n, slot in enumerate(slots):
        kf = m.keyframes[slot]
        bad_rows = obs.point[bad & (obs.keyframe == n)]
        if len(bad_rows):
            kf.point_ids[np.isin(kf.point_ids, bad_rows)] = -1
    newest = len(m.keyframes) - 1
    bad_newest = obs.point[bad & (obs.keyframe == np.searchsorted(slots, newest))] if newest in slots else []
    if len(bad_newest):
        s.tracks = s.tracks.subset(~np.isin(s.tracks.rows, bad_newest))
    renumber_tracks(s, m.forget_unobserved())


def move_map(s: VoState, transform: np.ndarray, scale: float) -> None:
    """Move the local map by the similarity x -> R (scale x) + t of `transform` (rigid 4x4): the poses stay
    rigid, their positions scale."""
    R, t = transform[:3, :3], transform[:3, 3]
    m = s.map
    m.positions = scale * m.positions @ R.T + t
    for kf in m.keyframes:
        pose = kf.pose.copy()
        pose[:3, :3] = R @ kf.pose[:3, :3]
        pose[:3, 3] = scale * R @ kf.pose[:3, 3] + t
        kf.pose = rigid(pose)


def median_depth(s: VoState, kf: Keyframe) -> float:
    """Median depth of the keyframe's map points in its camera (1 without points)."""
    rows = kf.point_ids[kf.point_ids >= 0]
    if len(rows) == 0:
        return 1.0
    return float(np.median(to_camera(s.map.positions[rows], kf.pose)[:, 2]))


def sparse_depth(s: VoState, kf: Keyframe, camera: Intrinsics) -> np.ndarray:
    """z-depth of the keyframe's points at their pixels, 0 elsewhere."""
    has = np.flatnonzero(kf.point_ids >= 0)
    return sparse_depth_image(s.map.positions[kf.point_ids[has]], kf.features.keypoints[has], kf.pose, camera)
