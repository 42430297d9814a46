"""The transform that takes a session's own world into a stored map's world, from frames located in the map.

A session in a map tracks in its own world from its first frame. Each verified fix (`MapFix`: the frame's pose in
the map) beside the frame's own pose measures that transform. A fix alone anchors the session only when the
frame's own depth confirms it (`confirmed`: many inliers, nearly all where the depth sees them; such a match does
not happen by chance); otherwise the session anchors once `agreeing` fixes of different frames give the same
transform (within `position_tolerance` of the scene's depth and `angle_tolerance_deg`). A metric session (sensor
depth or device poses) measures a rigid transform from each fix; an up-to-scale one (RGB only) needs fixes apart
from each other to measure the scale, and fits one similarity to all of them (rotation averaged, then scale and
translation by least squares on camera centres). Where a fix comes with the scale the frame's own points measure
against the map's depth (`scale`), it gives a similarity of its own, and two such fixes of different frames that
agree (scale included, within `scale_tolerance`) anchor the session without a baseline.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from worker.geometry.align import fit_similarity

from .localizer import MapFix

# A fix the frame's depth confirms (see `confirmed`) anchors a metric session alone.
CONFIRMED_INLIERS = 100
CONFIRMED_DEPTH_AGREEMENT = 0.9


def _inverse(T: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 similarity [sR | t]."""
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    R = T[:3, :3] / scale
    out = np.eye(4)
    out[:3, :3] = R.T / scale
    out[:3, 3] = -(R.T @ T[:3, 3]) / scale
    return out


def _rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


@dataclass
class Observation:
    """One located frame: its own-world pose (rigid, or a similarity after corrections) and its pose in the map."""

    frame: int
    own: np.ndarray
    in_map: np.ndarray
    inliers: int
    scene_depth: float
    scale: float | None = None  # map units per own unit, measured from the frame's depth (up to scale only)


@dataclass
class MapAnchoring:
    """Collects fixes until they agree on the own-world -> map-world transform (see the module docstring)."""

    metric: bool
    agreeing: int = 2
    position_tolerance: float = 0.05  # of the scene's depth
    angle_tolerance_deg: float = 3.0
    min_baseline: float = 0.1  # up to scale: camera centres this far apart (of the scene's depth) measure the scale
    scale_tolerance: float = 0.05  # up to scale: two fixes' depth-measured scales agree within this (relative)
    keep: int = 8
    transform: np.ndarray | None = None
    observations: list[Observation] = field(default_factory=list)

    @property
    def anchored(self) -> bool:
        return self.transform is not None

    def propose(self, frame: int, own_pose: np.ndarray, fix: MapFix, scene_depth: float,
                scale: float | None = None) -> np.ndarray | None:
        """Add a fix of `frame` (own-world pose `own_pose`; up to scale, with the `scale` its depth measured, if
        any); the transform when the fixes agree now (or this one is confirmed by the frame's depth), else None."""
        if self.anchored:
            return None
        self.observations.append(Observation(int(frame), np.asarray(own_pose, np.float64), fix.pose,
                                             fix.inliers, max(float(scene_depth), 1e-6),
                                             None if self.metric or scale is None else float(scale)))
        self.observations = self.observations[-self.keep:]
        if self.metric and confirmed(fix):
            transform = fix.pose @ _inverse(np.asarray(own_pose, np.float64))
        elif self.metric:
            transform = self._rigid_agreement()
        else:
            transform = self._scaled_agreement()
            if transform is None:
                transform = self._similarity_agreement()
        if transform is not None:
            self.transform = transform
        return transform

    def _rigid_agreement(self) -> np.ndarray | None:
        """The newest fix's transform when `agreeing - 1` other frames' fixes give the same one."""
        newest = self.observations[-1]
        candidate = newest.in_map @ _inverse(newest.own)
        agree = [o for o in self.observations[:-1] if o.frame != newest.frame
                 and self._same(candidate, o.in_map @ _inverse(o.own), newest.scene_depth)]
        if len(agree) + 1 < self.agreeing:
            return None
        best = max([newest, *agree], key=lambda o: o.inliers)
        return best.in_map @ _inverse(best.own)

    def _scaled_agreement(self) -> np.ndarray | None:
        """Up to scale: the newest fix's similarity (its depth-measured scale) when another frame's agrees."""
        newest = self.observations[-1]
        if newest.scale is None:
            return None
        candidate = _scaled_transform(newest)
        agree = [o for o in self.observations[:-1] if o.scale is not None and o.frame != newest.frame
                 and abs(np.log(o.scale / newest.scale)) <= np.log1p(self.scale_tolerance)
                 and self._same(candidate, _scaled_transform(o), newest.scene_depth)]
        if len(agree) + 1 < max(self.agreeing - 1, 2):
            return None
        return _scaled_transform(max([newest, *agree], key=lambda o: o.inliers))

    def _same(self, a: np.ndarray, b: np.ndarray, scene_depth: float) -> bool:
        delta = _inverse(a) @ b
        return (np.linalg.norm(delta[:3, 3]) <= self.position_tolerance * scene_depth
                and _rotation_angle_deg(delta[:3, :3] / np.cbrt(np.linalg.det(delta[:3, :3])))
                <= self.angle_tolerance_deg)

    def _similarity_agreement(self) -> np.ndarray | None:
        """One similarity fitted to the fixes that explain each other: fitted to all, the fix it explains worst
        dropped while some are off (a fix of a frame tracked before the odometry settled, say), as long as
        `agreeing` of them remain and span a baseline."""
        obs = list(self.observations)
        depth = float(np.median([o.scene_depth for o in obs]))
        while len(obs) >= max(self.agreeing, 2):
            map_centres = np.stack([o.in_map[:3, 3] for o in obs])
            if np.linalg.norm(map_centres - map_centres.mean(0), axis=1).max() < self.min_baseline * depth:
                return None
            transform = fit_similarity([o.own for o in obs], [o.in_map for o in obs])
            if transform is None:
                return None
            scale = float(np.cbrt(np.linalg.det(transform[:3, :3])))
            if not np.isfinite(scale) or scale <= 0:
                return None
            off = [self._similarity_miss(transform, o, depth) for o in obs]
            if max(off) <= 1.0:
                return transform
            del obs[int(np.argmax(off))]
        return None

    def _similarity_miss(self, transform: np.ndarray, o: Observation, depth: float) -> float:
        """How far `transform` takes the fix's own pose from its pose in the map, in tolerances (<= 1: within)."""
        moved = transform @ o.own
        rotation = moved[:3, :3] / np.cbrt(np.linalg.det(moved[:3, :3]))
        return max(float(np.linalg.norm(moved[:3, 3] - o.in_map[:3, 3])) / (self.position_tolerance * depth),
                   _rotation_angle_deg(rotation.T @ o.in_map[:3, :3]) / self.angle_tolerance_deg)

    def state_dict(self) -> dict[str, Any]:
        return {"transform": self.transform,
                "observations": [{"frame": o.frame, "own": o.own, "in_map": o.in_map, "inliers": o.inliers,
                                  "scene_depth": o.scene_depth, "scale": o.scale} for o in self.observations]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.transform = None if state.get("transform") is None else np.asarray(state["transform"], np.float64)
        self.observations = [Observation(int(o["frame"]), np.asarray(o["own"], np.float64),
                                         np.asarray(o["in_map"], np.float64), int(o["inliers"]),
                                         float(o["scene_depth"]),
                                         None if o.get("scale") is None else float(o["scale"]))
                             for o in state.get("observations") or []]


def confirmed(fix: MapFix) -> bool:
    """Whether the frame's own depth confirms a fix beyond doubt: at least CONFIRMED_INLIERS inliers and
    CONFIRMED_DEPTH_AGREEMENT of them where the depth sees them."""
    return (fix.depth_agreement is not None and fix.depth_agreement >= CONFIRMED_DEPTH_AGREEMENT
            and fix.inliers >= CONFIRMED_INLIERS)


def _scaled_transform(o: Observation) -> np.ndarray:
    """The similarity S (scale `o.scale`) with S @ own ~ in_map for one fix: rotation and camera centre exact."""
    own_rotation = o.own[:3, :3] / np.cbrt(np.linalg.det(o.own[:3, :3]))
    R = o.in_map[:3, :3] @ own_rotation.T
    out = np.eye(4)
    out[:3, :3] = o.scale * R
    out[:3, 3] = o.in_map[:3, 3] - o.scale * R @ o.own[:3, 3]
    return out
