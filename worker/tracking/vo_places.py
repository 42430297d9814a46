"""Visual odometry's places to come back to: the ORB features of a frame (extracted once), keyframes as places
(their ORB keypoints on map points), keyframes leaving the map kept as places, and the places worth an XFeat pass
for a lost frame."""

from __future__ import annotations

from itertools import zip_longest

import numpy as np

from .features import Features
from .keyframe_archive import ArchivedKeyframe
from .learned_places import nearest_within
from .local_map import Keyframe
from .relocalization import Place
from .vo_state import VoParts, VoState


def orb_features(s: VoState, parts: VoParts, index: int, gray: np.ndarray) -> Features:
    """ORB features of frame `index` (extracted once per frame)."""
    if s.orb_of is None or s.orb_of[0] != index:
        s.orb_of = (index, parts.extractor.extract(gray))
    return s.orb_of[1]


def place_rows(parts: VoParts, kf: Keyframe) -> tuple[np.ndarray, np.ndarray]:
    """The keyframe's ORB keypoints (indices) that lie on one of its map points' observations (within the
    relocalisation tolerance), and those points' rows."""
    has = np.flatnonzero(kf.point_ids >= 0)
    orb = kf.orb
    if len(has) == 0 or len(orb) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    radius = parts.config.place_radius_px * parts.extractor.level_sigmas(orb.octaves)
    near, nearest = nearest_within(orb.keypoints, kf.features.keypoints[has], radius)
    return near, kf.point_ids[has[nearest]]


def place_of(s: VoState, parts: VoParts, kf: Keyframe,
             matched: tuple[np.ndarray, np.ndarray] | None = None) -> Place:
    """The keyframe's ORB keypoints that lie on one of its map points' observations, with those points
    (`matched`: its `place_rows`, when already found)."""
    near, rows = place_rows(parts, kf) if matched is None else matched
    orb = kf.orb
    return Place(kf.index, kf.pose.copy(), orb.keypoints[near], orb.descriptors[near],
                 s.map.positions[rows].copy(), map_id=s.map_id, output=s.output.copy(),
                 gray=s.keyframe_images.get(kf.index))


def _archive_one(s: VoState, kf: Keyframe, near: np.ndarray, orb_rows: np.ndarray) -> None:
    """Keep one keyframe's observations and its ORB keypoints `near` on the points `orb_rows` (`place_rows`)."""
    m = s.map
    has = np.flatnonzero(kf.point_ids >= 0)
    rows = kf.point_ids[has]
    s.archive.record(ArchivedKeyframe(kf.index, kf.pose.copy(), kf.features.keypoints[has].astype(np.float32),
                                      m.ids[rows], kf.features.octaves[has], kf.orb.keypoints[near],
                                      kf.orb.descriptors[near], m.ids[orb_rows]),
                     dict(zip(m.ids[rows].tolist(), m.positions[rows].copy(), strict=True)), m.generation)


def archive(s: VoState, parts: VoParts, keyframes: list[Keyframe]) -> None:
    """Keep the keyframes' observations for the final bundle adjustment (their point rows still valid)."""
    if s.archive.max_keyframes:
        for kf in keyframes:
            _archive_one(s, kf, *place_rows(parts, kf))


def retire(s: VoState, parts: VoParts, keyframes: list[Keyframe]) -> None:
    """Keyframes leaving the map become places (and are archived); the newest `learned_places` keep their
    image."""
    matched = [place_rows(parts, kf) for kf in keyframes]  # once a keyframe: both uses need them
    if s.archive.max_keyframes:
        for kf, (near, orb_rows) in zip(keyframes, matched, strict=True):
            _archive_one(s, kf, near, orb_rows)
    places = (place_of(s, parts, kf, m) for kf, m in zip(keyframes, matched, strict=True))
    s.retired.extend(p for p in places if len(p.points) >= parts.config.reloc_min_inliers)
    del s.retired[: max(0, len(s.retired) - parts.config.reloc_keyframes)]
    for place in s.retired[: max(0, len(s.retired) - parts.config.learned_places)]:
        place.gray = None
    parts.learned.forget({p.index for p in s.retired if p.gray is not None}
                         | {kf.index for kf in s.map.keyframes})


def learned_candidates(s: VoState, parts: VoParts, index: int, gray: np.ndarray, places: list[Place] | None = None,
                       by_words: bool = True) -> list[Place]:
    """Remembered keyframes with an image to match a lost frame to by XFeat: the `learned_candidates` nearest
    the last pose (viewing direction and position; a restarted map begins at the old map's last pose, so its
    coordinates are near the old map's until joined) and as many most alike in ORB words, without repeats,
    taken in turn (the most alike, the nearest, the second most alike, ...: a frame's network passes describe
    the likeliest of each kind first)."""
    c = parts.config
    if places is None:
        places = s.retired + [place_of(s, parts, kf) for kf in s.map.keyframes]
    places = [p for p in places if p.gray is not None and len(p.points) >= c.reloc_min_inliers]
    if not places:
        return []
    nearest = sorted(places, key=lambda p: pose_distance(s, p.pose, s.pose))[: c.learned_candidates]
    features = orb_features(s, parts, index, gray) if by_words else None
    if features is None or len(features) < c.min_features:
        return nearest
    alike = parts.recognizer.shortlist(features, places)[: c.learned_candidates]
    chosen: list[Place] = []
    for pair in zip_longest(alike, nearest):
        chosen += [p for p in pair if p is not None and p not in chosen]
    return chosen


def pose_distance(s: VoState, a: np.ndarray, b: np.ndarray) -> float:
    """How far apart two camera poses look: the angle between their viewing directions (radians) plus their
    distance in median scene depths."""
    turned = np.arccos(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))
    return float(turned + np.linalg.norm(a[:3, 3] - b[:3, 3]) / max(s.map_depth, 1e-6))
