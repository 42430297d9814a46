"""Visual odometry's maps joined: a map restarted after a loss moves into an older map's frame, scale included,
when one of its keyframes recognises an older place (`map_join`; ORB, else XFeat); the poses handed out take the
inverse move (the output similarity), so that they never jump."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from worker.events import Initialized, MapsMerged

from .base import TrackingResult
from .local_map import Keyframe
from .map_join import (
    MapLink,
    link_from_hit,
    link_maps,
    moved_points,
    moved_pose,
    similarity,
    similarity_inverse,
    similarity_scale,
)
from .relocalization import Place
from .vo_mapping import move_map
from .vo_places import learned_candidates, place_rows, pose_distance
from .vo_state import VoParts, VoState


def join_maps(s: VoState, parts: VoParts, index: int, kf: Keyframe, K: np.ndarray) -> list[MapsMerged]:
    """Try to join the restarted map to an older one at keyframe `kf` (see `map_join`): on a link, the map
    (keyframes, points, its remembered places) moves into the older map's frame, scale included, and the
    output transform takes the inverse move, so that poses handed out do not jump; the `maps_merged` event
    carries the Sim(3) edge for the pose graph (`relative`: this frame in the place's frame, each in the units
    of the poses handed out at the time) and `correction` (the similarity that takes the new map's output
    poses into the older map's)."""
    c, join = parts.config, s.join
    join.tried += 1
    if join.tried > c.join_max_keyframes:
        s.join = None
        return []
    places = [p for p in s.retired if p.map_id != s.map_id]
    near, rows = place_rows(parts, kf)
    points = np.full((len(kf.orb), 3), np.nan)
    points[near] = s.map.positions[rows]
    link = link_maps(parts.recognizer, kf.orb, points, kf.pose, places, K,
                     parts.extractor.level_sigmas(kf.orb.octaves), c.reloc_min_inliers, c.join_min_pairs,
                     c.join_max_spread)
    method = "orb"
    if link is None and c.learned_join:
        link, method = learned_link(s, parts, index, kf, places, K), "learned"
    if link is None:
        return []
    S, scale = link.transform, link.scale
    before = s.output
    # Each camera with its output units (1 / the output scale of its time, in the older map's units).
    place_camera = link.place.pose @ similarity(np.eye(3), np.zeros(3), 1.0 / similarity_scale(link.place.output))
    kf_camera = S @ kf.pose @ similarity(np.eye(3), np.zeros(3), 1.0 / similarity_scale(before))
    relative = similarity_inverse(place_camera) @ kf_camera
    correction = link.place.output @ S @ similarity_inverse(before)
    move_map(s, similarity(S[:3, :3] / scale, S[:3, 3], 1.0), scale)
    for place in s.retired:
        if place.map_id == s.map_id:
            place.pose, place.points = moved_pose(S, place.pose), moved_points(S, place.points)
            place.output, place.map_id = place.output @ similarity_inverse(S), link.place.map_id
    s.output = before @ similarity_inverse(S)
    s.velocity[:3, 3] *= scale
    s.map_id, s.join = link.place.map_id, None
    return [MapsMerged(frame=index, place=link.place.index, since=join.since, scale=similarity_scale(correction),
                       pairs=link.pairs, spread=round(link.spread, 4), method=method, relative=relative.tolist(),
                       correction=correction.tolist())]


def learned_link(s: VoState, parts: VoParts, index: int, kf: Keyframe, places: list[Place], K: np.ndarray
                 ) -> MapLink | None:
    """The join by XFeat where ORB found no place: the keyframe's XFeat keypoints and its own map points,
    described by XFeat, matched to the older maps' places nearest its pose (`learned_join_reach`), verified by
    PnP; the inliers on its own map points measure the scale."""
    c = parts.config
    # A restarted map begins at the old map's last pose: only places near the keyframe there are worth a network
    # pass (the maps' coordinates agree roughly until joined; far places are left to ORB and loop closure).
    places = [p for p in places if pose_distance(s, p.pose, kf.pose) <= c.learned_join_reach]
    candidates = learned_candidates(s, parts, index, s.keyframe_images[kf.index], places, by_words=False)
    if not candidates:
        return None
    has = np.flatnonzero(kf.point_ids >= 0)  # the keyframe's own map points, described where it tracks them
    current = parts.learned.of_frame(kf.index, s.keyframe_images[kf.index], kf.features.keypoints[has])
    if current is None:
        return None
    hit = parts.learned.relocalise(current, candidates, K)
    if hit is None:
        return None
    points = np.full((len(current), 3), np.nan)
    points[len(current) - len(has):] = s.map.positions[kf.point_ids[has]]
    return link_from_hit(hit, points, kf.pose, places, c.join_min_pairs, c.join_max_spread)


def output_is_identity(s: VoState) -> bool:
    """Whether poses are handed out in the map's coordinates (no restarted map joined an older one yet)."""
    return bool(np.array_equal(s.output, np.eye(4)))


def to_output(s: VoState, result: TrackingResult) -> TrackingResult:
    """The result in the output's coordinates (the map's, until a restarted map joined an older one)."""
    if output_is_identity(s):
        return result
    result.pose = moved_pose(s.output, result.pose)
    if result.depth is not None:
        result.depth = result.depth * np.float32(similarity_scale(s.output))
    result.events = [replace(e, frames=[[i, moved_pose(s.output, np.asarray(p)).tolist()] for i, p in e.frames])
                     if isinstance(e, Initialized) and e.frames else e for e in result.events]
    return result
