"""Incremental registration of photos, one at a time, as structure from motion does it: the first pair with enough
parallax makes a two-view map; every later photo is matched against the latest registered ones, posed by PnP on
the points its keypoints match, matched again against every registered photo looking the same way (the revisits of
an orbit), and its new matches are triangulated; a local bundle adjustment follows each photo, a global one each
time the reconstruction has grown by a share."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..pose_optimization import pnp_pose
from ..projection import invert_pose
from ..two_view import two_view_from_matches
from ..vo_config import VisualOdometryConfig
from .adjustment import adjust, window_around
from .config import PhotoRegistrationConfig
from .features import PhotoFeatures
from .growth import Matches, join_known_points, triangulate_matches
from .matching import mutual_matches
from .reconstruction import Reconstruction, RegisteredPhoto


@dataclass
class Registration:
    """What adding a photo did. state: "waiting" (no map yet), "initialized" (the two-view map was made),
    "registered", "unregistered" (no pose). pose: camera-to-world, None unless posed. posed: other photos given a
    pose now (frame index -> pose: the photos that waited for the first map). inliers: PnP inliers."""

    state: str
    pose: np.ndarray | None = None
    posed: dict[int, np.ndarray] = field(default_factory=dict)
    inliers: int = 0
    reason: str = ""


class IncrementalRegistration:
    """Photos in, poses out (see the module docstring). The world is the first map's first photo; its scale makes
    that map's median depth 1."""

    def __init__(self, K: np.ndarray, config: PhotoRegistrationConfig | None = None) -> None:
        self.K = K
        self.config = config or PhotoRegistrationConfig()
        self.map = Reconstruction()
        self.waiting: list[tuple[int, PhotoFeatures]] = []
        self.unregistered: list[tuple[int, PhotoFeatures]] = []  # tried again after each registration
        self.globally_adjusted_at = 0

    @property
    def started(self) -> bool:
        return bool(self.map.photos)

    def add(self, index: int, features: PhotoFeatures) -> Registration:
        """Register photo `index` with its features."""
        if not self.started:
            return self._initialise(index, features)
        done = self._register(index, features)
        if done.pose is None:
            self.unregistered = (self.unregistered + [(index, features)])[-self.config.retry_photos:]
        elif self.unregistered:
            done.posed.update(self._retry())
        return done

    def _retry(self) -> dict[int, np.ndarray]:
        """The photos that could not be registered, tried again, newest first, until none more registers (a
        revisit from the other side places the photos after a gap); returns the poses found."""
        posed: dict[int, np.ndarray] = {}
        progress = True
        while progress and self.unregistered:
            progress = False
            for item in reversed(list(self.unregistered)):
                again = self._register(*item)
                if again.pose is not None:
                    posed[item[0]] = again.pose
                    self.unregistered.remove(item)
                    progress = True
        return posed

    # -- the first map -------------------------------------------------------------------------------------------
    def _initialise(self, index: int, features: PhotoFeatures) -> Registration:
        c = self.config
        two_view_config = VisualOdometryConfig(chi2_px=c.chi2_px, min_parallax_deg=c.min_parallax_deg)
        reason = "no photo to pair with yet"
        for n, (ref_index, ref) in enumerate(self.waiting):
            ia, ib = mutual_matches(ref, features, c.match_ratio)
            ones = np.ones(len(ia))
            attempt = two_view_from_matches(ref.keypoints[ia], features.keypoints[ib], self.K, two_view_config,
                                            ones, ones, ia, ib)
            if attempt.map is None:
                reason = attempt.reason
                continue
            two = attempt.map
            a = self.map.add_photo(RegisteredPhoto(ref_index, ref, np.eye(4)))
            b = self.map.add_photo(RegisteredPhoto(index, features, two.pose_b))
            ids = self.map.add_points(two.points)
            self.map.observe(a, two.ia, ids)
            self.map.observe(b, two.ib, ids)
            adjust(self.map, self.K, np.array([b]), np.array([a]), c.ba_iterations, c.chi2_px)
            for item in self.waiting[:n] + self.waiting[n + 1:]:  # the photos that waited
                if self._register(*item).pose is None:
                    self.unregistered.append(item)
            self.waiting = []
            self._anchor_at_first_photo()
            posed = {p.index: p.pose.copy() for p in self.map.photos if p.index != index}
            return Registration("initialized", self.map.photos[b].pose.copy(), posed, len(two.points))
        self.waiting = (self.waiting + [(index, features)])[-c.waiting_photos:]
        return Registration("waiting", reason=reason)

    def _anchor_at_first_photo(self) -> None:
        """Move the reconstruction so that the earliest registered photo is at the origin (the session's first frame
        is its first keyframe, at the origin, whichever pair made the map)."""
        m = self.map
        first = min(range(len(m.photos)), key=lambda s: m.photos[s].index)
        move = invert_pose(m.photos[first].pose)
        for photo in m.photos:
            photo.pose = move @ photo.pose
        m.points = m.points @ move[:3, :3].T + move[:3, 3]

    # -- a photo on the map --------------------------------------------------------------------------------------
    def _register(self, index: int, features: PhotoFeatures) -> Registration:
        c, m = self.config, self.map
        order = list(range(len(m.photos)))[::-1]
        latest, rest = order[: c.neighbours], order[c.neighbours:]
        matches = {slot: mutual_matches(m.photos[slot].features, features, c.match_ratio) for slot in latest}
        found = self._pnp(features, matches)
        if found is None and rest:  # a jump: every registered photo
            matches.update({slot: mutual_matches(m.photos[slot].features, features, c.match_ratio) for slot in rest})
            found = self._pnp(features, matches)
        if found is None:
            return Registration("unregistered", reason="too few matches to the registered photos' points")
        pose, keypoints, points = found
        slot = m.add_photo(RegisteredPhoto(index, features, pose))
        m.observe(slot, keypoints, points)
        for other in self._looking_the_same_way(slot, exclude=set(matches)):
            matches[other] = mutual_matches(m.photos[other].features, features, c.match_ratio)
        join_known_points(m, self.K, c.chi2_px, slot, matches)
        triangulate_matches(m, self.K, c.chi2_px, c.min_parallax_deg, slot, matches)
        adjust(m, self.K, window_around(m, slot, c.local_window), np.zeros(0, np.int64), c.ba_iterations, c.chi2_px)
        if len(m.photos) >= (1 + c.global_every) * max(self.globally_adjusted_at, 2):
            self.adjust_all()
        return Registration("registered", m.photos[slot].pose.copy(), inliers=len(keypoints))

    def _pnp(self, features: PhotoFeatures, matches: Matches
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Pose of a new photo from its matches to the registered photos' points: (pose, keypoints, points)."""
        m, c = self.map, self.config
        keypoint_to_point: dict[int, int] = {}
        for slot, (i_old, i_new) in matches.items():
            point = m.photos[slot].point_of[i_old]
            for k, p in zip(i_new[point >= 0].tolist(), point[point >= 0].tolist()):
                keypoint_to_point.setdefault(k, p)
        if len(keypoint_to_point) < c.min_inliers:
            return None
        keypoints = np.fromiter(keypoint_to_point.keys(), np.int64)
        points = np.fromiter(keypoint_to_point.values(), np.int64)
        result = pnp_pose(m.points[points], features.keypoints[keypoints], self.K, np.ones(len(points)),
                          c.chi2_px, c.min_inliers)
        if result is None:
            return None
        pose, inlier = result
        return pose, keypoints[inlier], points[inlier]

    def _looking_the_same_way(self, slot: int, exclude: set[int]) -> list[int]:
        """The `revisits` registered photos nearest photo `slot` (not in `exclude`) whose optical axis is within
        `view_angle_deg` of its own."""
        me = self.map.photos[slot].pose
        cos = np.cos(np.deg2rad(self.config.view_angle_deg))
        near = [(float(np.linalg.norm(p.pose[:3, 3] - me[:3, 3])), s) for s, p in enumerate(self.map.photos)
                if s != slot and s not in exclude and float(p.pose[:3, 2] @ me[:3, 2]) >= cos]
        return [s for _, s in sorted(near)[: self.config.revisits]]

    def adjust_all(self) -> None:
        """Every photo adjusted together with every point, the session's first photo held (the origin)."""
        m = self.map
        first = min(range(len(m.photos)), key=lambda s: m.photos[s].index)
        others = np.array([s for s in range(len(m.photos)) if s != first])
        adjust(m, self.K, others, np.array([first]), self.config.ba_iterations, self.config.chi2_px)
        self.globally_adjusted_at = len(m.photos)
