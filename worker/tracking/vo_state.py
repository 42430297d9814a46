"""What monocular visual odometry changes while it tracks (`VoState`), with its snapshot format, and the parts it
tracks with that do not change (`VoParts`: the settings and the feature and place machinery built from them).

The phases (`vo_initialisation`, `vo_frame_tracking`, `vo_mapping`, `vo_map_join`, `vo_recovery`,
`vo_calibration`) are functions of these two; `visual_odometry.VisualOdometry` sequences them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from worker.geometry import Intrinsics

from .features import Features, OrbExtractor
from .keyframe_archive import KeyframeArchive
from .learned_places import LearnedPlaces
from .local_map import LocalMap
from .projection import to_camera
from .relocalization import Place, PlaceRecognizer
from .self_calibration import FocalEstimator
from .tracks import Tracks
from .vo_config import VisualOdometryConfig

STATE_VERSION = 3
MIN_SHARED_FOR_SCALE = 10  # old map points a restarted map must share to take its scale from them


@dataclass
class Anchor:
    """The last tracked frame of a lost map: index, pose, track ids [N] (ascending), pixels [N, 2] and the world
    points [N, 3] its tracks measured (NaN: none)."""

    index: int
    pose: np.ndarray
    ids: np.ndarray
    uv: np.ndarray
    points: np.ndarray
    velocity: np.ndarray  # the camera motion per frame when tracking broke
    predicted: np.ndarray  # where the motion model puts the latest frame the tracks were followed into
    gray: np.ndarray  # its image (learned relocalisation describes its map points there)
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 64), np.float32))  # XFeat, lazily ...
    world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # ... of keypoints on these map points
    described: bool = False  # whether XFeat described it (it may have no keypoint on a map point)

    def scale_of(self, points: np.ndarray, rows: np.ndarray) -> tuple[float, int]:
        """Scale from a new map (`points` [n, 3] in the anchor camera's frame, on the anchor's tracks `rows` [n])
        to the old one, and how many shared points gave it (0: the old points' median depth did)."""
        old = self.points[rows]
        has = np.isfinite(old).all(axis=1) & (points[:, 2] > 0)
        if has.sum() >= MIN_SHARED_FOR_SCALE:
            depth = to_camera(old[has], self.pose)[:, 2]
            ratio = depth / points[has, 2]
            ratio = ratio[ratio > 0]
            if len(ratio) >= MIN_SHARED_FOR_SCALE:
                return float(np.median(ratio)), len(ratio)
        seen = self.points[np.isfinite(self.points).all(axis=1)]
        depth = to_camera(seen, self.pose)[:, 2]
        depth = depth[depth > 0]
        old_median = float(np.median(depth)) if len(depth) else 1.0
        return old_median / max(float(np.median(points[:, 2])), 1e-9), 0

    def to_state(self) -> dict[str, Any]:
        return {"index": self.index, "pose": self.pose, "ids": self.ids, "uv": self.uv, "points": self.points,
                "velocity": self.velocity, "predicted": self.predicted, "gray": self.gray,
                "descriptors": self.descriptors, "world": self.world}

    @classmethod
    def from_state(cls, s: dict[str, Any]) -> Anchor:
        return cls(int(s["index"]), np.asarray(s["pose"], np.float64).reshape(4, 4),
                   np.asarray(s["ids"], np.int64).reshape(-1), np.asarray(s["uv"], np.float32).reshape(-1, 2),
                   np.asarray(s["points"], np.float64).reshape(-1, 3),
                   np.asarray(s["velocity"], np.float64).reshape(4, 4),
                   np.asarray(s["predicted"], np.float64).reshape(4, 4), np.asarray(s["gray"], np.uint8),
                   np.asarray(s["descriptors"], np.float32).reshape(-1, 64),
                   np.asarray(s["world"], np.float64).reshape(-1, 3))


@dataclass
class JoinState:
    """A map restarted after a loss, not joined to an older map yet: its first frame and the keyframes tried."""

    since: int
    tried: int = 0


@dataclass
class VoParts:
    """What visual odometry tracks with and never changes: its settings, the ORB extractor, the ORB place
    recogniser and XFeat matching against remembered keyframes (computed only when flow and ORB failed)."""

    config: VisualOdometryConfig
    extractor: OrbExtractor
    recognizer: PlaceRecognizer
    learned: LearnedPlaces

    @classmethod
    def build(cls, config: VisualOdometryConfig) -> VoParts:
        extractor, recognizer = OrbExtractor(config), PlaceRecognizer(config)
        c = config
        learned = LearnedPlaces(c.learned_keypoints, c.learned_min_similarity, c.chi2_px, c.reloc_min_inliers,
                                c.learned_passes_per_frame, c.learned_threads, c.learned_glue_keypoints,
                                c.learned_glue_min_confidence, c.learned_glue_candidates,
                                c.learned_glue_point_inliers)
        return cls(config, extractor, recognizer, learned)


def _image(gray: np.ndarray | None) -> np.ndarray:
    """An image for the snapshot (none: an empty one)."""
    return np.zeros((0, 0), np.uint8) if gray is None else gray


@dataclass
class VoState:
    """Everything visual odometry changes while tracking: a fresh one (`start`) is a session's beginning."""

    focal: FocalEstimator  # the focal length of an uncalibrated camera, measured before the first map
    # (frame index, pose) of the engine's keyframes, to come back to
    engine_keyframes: deque[tuple[int, np.ndarray]]
    status: str = "initializing"  # | "tracking" | "lost"
    map: LocalMap = field(default_factory=LocalMap)
    retired: list[Place] = field(default_factory=list)  # keyframes that left the window, kept for relocalisation
    keyframe_images: dict[int, np.ndarray] = field(default_factory=dict)  # the map keyframes' images (learned)
    orb_of: tuple[int, Features] | None = None  # the last frame's ORB features, extracted on demand
    tracks: Tracks = field(default_factory=Tracks.empty)
    next_id: int = 0
    previous_gray: np.ndarray | None = None  # the last frame tracked (flow starts from it)
    keyframe_gray: np.ndarray | None = None  # the last keyframe's image (tracks are refined against it)
    pending: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # (index, ids, uv) waiting
    pending_orientation: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> orientation held
    init_state: str = ""  # what initialisation waits for ("rotation_only", "waiting_for_parallax", ...)
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    velocity: np.ndarray = field(default_factory=lambda: np.eye(4))  # camera motion of the last frame ...
    velocity_at: int = -1  # ... and the frame it was measured at (by two tracked frames; resets do not count)
    frames_since_keyframe: int = 0
    tracked_at_keyframe: int = 0
    lost_since: int | None = None
    rotation_since: int | None = None  # first frame of the current rotation-only run
    direct_since: int | None = None  # first frame of the current run placed by image alignment ...
    direct_depth: float = 1.0  # ... and the scene depth where it began
    parallax_seen: bool = False  # whether this frame's tracks showed the rotation-only run's translation
    last_tracked: int = -1  # index of the last tracked frame
    mapped_at_loss: int = 0  # tracks of map points when tracking was lost
    anchor: Anchor | None = None  # the last tracked frame's tracks, while lost: a map restarts from them
    maps_started: int = 1  # maps begun by an initialisation: the first, and each new map after a loss
    map_origin: np.ndarray = field(default_factory=lambda: np.eye(4))  # where the next map's reference is placed
    map_depth: float = 1.0  # ... and the median scene depth it is given (the old map's, after a loss)
    image_size: tuple[int, int] | None = None
    estimated_intrinsics: Intrinsics | None = None
    # Maps: the current one's id, how many were made, and the similarity from the map's coordinates to the poses
    # handed out (it changes when a restarted map joins an older one, so that poses never jump).
    map_id: int = 0
    maps_made: int = 1
    output: np.ndarray = field(default_factory=lambda: np.eye(4))
    join: JoinState | None = None
    # every keyframe made, for the final bundle adjustment (memory only: not in the snapshot)
    archive: KeyframeArchive = field(default_factory=lambda: KeyframeArchive(0))

    @classmethod
    def start(cls, config: VisualOdometryConfig) -> VoState:
        return cls(FocalEstimator(config), deque(maxlen=max(1, config.reuse_keyframes)),
                   archive=KeyframeArchive(config.final_adjustment_keyframes if config.final_adjustment else 0))

    def state_dict(self) -> dict[str, Any]:
        """The snapshot's fields (msgpack-able; bounded by the window and the place memory), in their order, without
        the version and the configuration `VisualOdometry.state_dict` puts first."""
        return {
            "status": self.status,
            "pose": self.pose, "velocity": self.velocity, "frames_since_keyframe": self.frames_since_keyframe,
            "tracked_at_keyframe": self.tracked_at_keyframe,
            "lost_since": -1 if self.lost_since is None else self.lost_since,
            "rotation_since": -1 if self.rotation_since is None else self.rotation_since,
            "direct_since": -1 if self.direct_since is None else self.direct_since,
            "direct_depth": self.direct_depth, "velocity_at": self.velocity_at,
            "image_size": [] if self.image_size is None else list(self.image_size),
            "focal": self.focal.state_dict(),
            "estimated_intrinsics": {} if self.estimated_intrinsics is None else self.estimated_intrinsics.to_dict(),
            "pending": [{"index": i, "ids": ids, "uv": uv, "orientation": self.pending_orientation.get(i, np.eye(3))}
                        for i, ids, uv in self.pending],
            "init_state": self.init_state, "last_tracked": self.last_tracked, "mapped_at_loss": self.mapped_at_loss,
            "anchor": {} if self.anchor is None else self.anchor.to_state(),
            "previous_gray": _image(self.previous_gray), "keyframe_gray": _image(self.keyframe_gray),
            "tracks": self.tracks.to_state(), "next_id": self.next_id,
            "map": self.map.to_state(), "retired": [p.to_state() for p in self.retired],
            "engine_keyframes": [{"index": i, "pose": p} for i, p in self.engine_keyframes],
            "maps_started": self.maps_started, "map_origin": self.map_origin, "map_depth": self.map_depth,
            "map_id": self.map_id, "maps_made": self.maps_made, "output": self.output,
            "join": {} if self.join is None else {"since": self.join.since, "tried": self.join.tried},
            "keyframe_images": [{"index": i, "gray": g} for i, g in self.keyframe_images.items()],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue a fresh state from `state_dict()` (keys a snapshot of an older version lacks keep their start
        values)."""
        self.status = str(state["status"])
        self.pose = np.asarray(state["pose"], np.float64).reshape(4, 4)
        self.velocity = np.asarray(state["velocity"], np.float64).reshape(4, 4)
        self.frames_since_keyframe = int(state["frames_since_keyframe"])
        self.tracked_at_keyframe = int(state["tracked_at_keyframe"])
        self.lost_since = None if int(state["lost_since"]) < 0 else int(state["lost_since"])
        self.rotation_since = None if int(state.get("rotation_since", -1)) < 0 else int(state["rotation_since"])
        self.direct_since = None if int(state.get("direct_since", -1)) < 0 else int(state["direct_since"])
        self.direct_depth = float(state.get("direct_depth", 1.0))
        self.velocity_at = int(state.get("velocity_at", -1))
        self.image_size = tuple(int(v) for v in state["image_size"]) or None
        self.focal.load_state_dict(state["focal"])
        if state["estimated_intrinsics"]:
            self.estimated_intrinsics = Intrinsics.from_dict(state["estimated_intrinsics"])
        self.pending = [(int(p["index"]), np.asarray(p["ids"], np.int64).reshape(-1),
                         np.asarray(p["uv"], np.float32).reshape(-1, 2)) for p in state["pending"]]
        self.pending_orientation = {int(p["index"]): np.asarray(p["orientation"], np.float64).reshape(3, 3)
                                    for p in state["pending"]}
        self.init_state = str(state["init_state"])
        self.last_tracked = int(state["last_tracked"])
        self.mapped_at_loss = int(state["mapped_at_loss"])
        self.anchor = Anchor.from_state(state["anchor"]) if state["anchor"] else None
        for name in ("previous_gray", "keyframe_gray"):
            gray = np.asarray(state[name], np.uint8)
            setattr(self, name, np.ascontiguousarray(gray) if gray.size else None)
        self.tracks = Tracks.from_state(state["tracks"])
        self.next_id = int(state["next_id"])
        self.map = LocalMap.from_state(state["map"])
        self.retired = [Place.from_state(p) for p in state["retired"]]
        self.engine_keyframes.extend((int(k["index"]), np.asarray(k["pose"], np.float64).reshape(4, 4))
                                     for k in state.get("engine_keyframes", []))
        self.maps_started = int(state.get("maps_started", 1))
        self.map_origin = np.asarray(state.get("map_origin", np.eye(4)), np.float64).reshape(4, 4)
        self.map_depth = float(state.get("map_depth", 1.0))
        self.map_id, self.maps_made = int(state.get("map_id", 0)), int(state.get("maps_made", 1))
        self.output = np.asarray(state.get("output", np.eye(4)), np.float64).reshape(4, 4)
        join = state.get("join") or {}
        self.join = JoinState(int(join["since"]), int(join["tried"])) if join else None
        self.keyframe_images = {int(k["index"]): np.ascontiguousarray(np.asarray(k["gray"], np.uint8))
                                for k in state.get("keyframe_images", [])}
