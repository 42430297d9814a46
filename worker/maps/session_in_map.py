"""A session that runs in a stored map: which map, how (`localize` or `extend`), the map's keyframes as the
localizer sees them, and how far the session's own world has been anchored in the map's.

The loop-closing stage owns it (worker.pipeline.loop_stage): it locates the frames tracking hands it
(`MapQuery`), anchors the session's world once fixes agree (worker.maps.anchoring) and moves the whole session into
the map's world then; later fixes of keyframes become pose-graph priors that hold the session to the map.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from protocol.map_package import MapPackage
from protocol.map_store import MAP_MODES, MapMode
from worker.loop.pose_graph import EdgeSigmas

from .anchoring import MapAnchoring
from .localizer import (
    LocalizerSettings,
    MapFix,
    MapLocalizer,
    MapView,
    describe_view,
    place_arrays,
    place_from_arrays,
)
from .stored_map import StoredMapRenderer
from .views import views_of_package

# A keyframe's fix in the map as a pose-graph prior: rotation (rad), translation (of the scene's depth), log-scale
# (free: an up-to-scale session's keyframes keep the scale the graph gives them).
PRIOR_ROTATION = 0.01
PRIOR_TRANSLATION = 0.01
PRIOR_LOG_SCALE = 1e3
log = logging.getLogger(__name__)
# A device-posed session's world transform is refined from this many keyframe fixes at a time, when they move it
# by more than this share of the scene's depth or this angle.
WORLD_REFINE_FIXES = 5
WORLD_REFINE_MIN = 0.003
WORLD_REFINE_MIN_DEG = 0.2
# An up-to-scale session's scale in the map from one frame (`depth_scale`): at least this many of its odometry's
# points where the stored map renders a depth, their log depth ratios within this median absolute deviation
DEPTH_SCALE_POINTS = 20
DEPTH_SCALE_SPREAD = 0.05
# Ids of the places other sessions share (apart from the map's keyframe ids)
SHARED_PLACE_IDS = 1 << 50


@dataclass
class MapQuery:
    """A frame to find in the stored map: its index, whether it is a keyframe (a graph node), its world pose when
    tracking made the query, its grey image, camera matrix and depth (own units; None without), how many
    corrections tracking had applied then (a world move made after that is not in `own_pose` yet) and, for an
    up-to-scale session, the points its odometry sees in it: [n, 3] pixel u, v and depth in the session's units."""

    frame: int
    keyframe: bool
    own_pose: np.ndarray
    gray: np.ndarray
    K: np.ndarray
    depth: np.ndarray | None = None
    corrections_seen: int = 0
    own_points: np.ndarray | None = None

    def state(self) -> dict[str, Any]:
        return {"kind": "map_query", "frame": self.frame, "keyframe": self.keyframe, "own_pose": self.own_pose,
                "gray": self.gray, "K": self.K, "depth": self.depth, "corrections_seen": self.corrections_seen,
                "own_points": self.own_points}

    @classmethod
    def from_state(cls, s: dict[str, Any]) -> MapQuery:
        depth, points = s.get("depth"), s.get("own_points")
        return cls(int(s["frame"]), bool(s["keyframe"]), np.asarray(s["own_pose"], np.float64),
                   np.asarray(s["gray"], np.uint8), np.asarray(s["K"], np.float64),
                   None if depth is None else np.asarray(depth, np.float32), int(s["corrections_seen"]),
                   None if points is None else np.asarray(points, np.float32).reshape(-1, 3))


class SessionInMap:
    """The stored map a session runs in (see the module docstring). `views` gives the map's keyframes (called once,
    in the loop-closing stage's thread); `map_metric`: the map's poses are metric. When the session's are too
    (`attach`), its world meets the map's by a rigid transform, else by a similarity."""

    def __init__(self, map_id: str, version: int, mode: MapMode, views: Callable[[], list[MapView]],
                 map_metric: bool = True, settings: LocalizerSettings | None = None) -> None:
        if mode not in MAP_MODES:
            raise ValueError(f"map mode must be one of {', '.join(MAP_MODES)}, got {mode!r}")
        self.map_id = map_id
        self.version = int(version)
        self.mode = mode
        self.map_metric = map_metric
        self.attach(session_metric=True)
        self.fixes = 0
        self.misses = 0
        self.shared_fixes = 0  # fixes among the places other sessions in the map shared (a loop between devices)
        self.relocalized_at: int | None = None  # the frame whose fix anchored the session
        self.package: MapPackage | None = None  # the stored map itself (`from_package`), for renders and merges
        self._renderer: StoredMapRenderer | None = None
        # Places shared live with the other sessions in the map (worker.runtime.map_exchange): this session's
        # keyframes once anchored (an `extend` session's), to publish; and how many the others' added here
        self._outgoing: list[dict[str, Any]] = []
        self.shared_received = 0
        self._views = views
        self._settings = settings
        self._localizer: MapLocalizer | None = None
        self._loading: threading.Thread | None = None
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()
        self.load_seconds: float | None = None

    @classmethod
    def from_package(cls, map_id: str, version: int, mode: MapMode, package: MapPackage | None) -> SessionInMap:
        """A session in the stored map `package` (None: the map is gone; the session keeps the world it was
        anchored in, and nothing more is located)."""
        if package is None:
            return cls(map_id, version, mode, list)
        in_map = cls(map_id, version, mode, lambda: views_of_package(package), map_metric=package.scale == "metric")
        in_map.package = package
        return in_map

    def renderer(self, own: Any) -> Any:
        """What the session's renders show: the stored map when it localizes in it, else its own map `own`."""
        if self.mode != "localize" or self.package is None:
            return own
        return self._stored_renderer()

    def _stored_renderer(self) -> StoredMapRenderer:
        with self._lock:
            if self._renderer is None:
                self._renderer = StoredMapRenderer(self.package)
            return self._renderer

    def depth_scale(self, fix: MapFix, query: MapQuery) -> float | None:
        """An up-to-scale session's scale in the map (map units per own unit) from one frame: the stored map's depth
        rendered at the fix over the depth of the points the session's odometry sees at the same pixels (median);
        None without such points, or where fewer than DEPTH_SCALE_POINTS of them meet the map or their ratios
        spread by more than DEPTH_SCALE_SPREAD (median absolute deviation of the log ratio)."""
        points = query.own_points
        if self.package is None or points is None or len(points) < DEPTH_SCALE_POINTS:
            return None
        height, width = query.gray.shape
        rendered = self._stored_renderer().render(fix.pose, torch.from_numpy(np.asarray(query.K, np.float32)),
                                                  width, height)
        depth = rendered.depth.detach().cpu().numpy().reshape(height, width)
        u = np.clip(points[:, 0].astype(np.int64), 0, width - 1)
        v = np.clip(points[:, 1].astype(np.int64), 0, height - 1)
        seen = depth[v, u]
        keep = (points[:, 2] > 0) & np.isfinite(seen) & (seen > 0)
        if keep.sum() < DEPTH_SCALE_POINTS:
            return None
        log_ratio = np.log(seen[keep] / points[keep, 2])
        centre = float(np.median(log_ratio))
        if float(np.median(np.abs(log_ratio - centre))) > DEPTH_SCALE_SPREAD:
            return None
        return float(np.exp(centre))

    def attach(self, session_metric: bool, device_poses: bool = False) -> None:
        """Set how the session's world meets the map's, once the session knows its input (its first frame);
        `device_poses`: its poses are a device's, rigidly tied to the map's world once anchored (so later fixes
        refine that one transform, `world_refinement`, rather than bend the trajectory)."""
        self.metric = bool(session_metric and self.map_metric)
        self.anchoring = MapAnchoring(metric=self.metric, agreeing=2 if self.metric else 3)
        self.device_poses = bool(device_poses)
        self._offsets: list[np.ndarray] = []

    def start_loading(self) -> None:
        """Build the map's places in a thread of their own now, so the first query finds them ready."""
        with self._lock:
            if self._localizer is not None or self._loading is not None:
                return
            self._loading = threading.Thread(target=lambda: self.localizer, name="map-places", daemon=True)
            self._loading.start()

    @property
    def anchored(self) -> bool:
        return self.anchoring.anchored

    @property
    def localizer(self) -> MapLocalizer:
        """The map's keyframes as places (built on first use, or by `start_loading`)."""
        with self._build_lock:
            if self._localizer is None:
                started = time.perf_counter()
                self._localizer = MapLocalizer(self._views(), self._settings)
                self.load_seconds = time.perf_counter() - started
            return self._localizer

    def locate(self, query: MapQuery) -> MapFix | None:
        """The query frame's verified pose in the map, or None (counted)."""
        fix = self.localizer.locate(query.gray, query.K, query.depth)
        if fix is None:
            self.misses += 1
        else:
            self.fixes += 1
            self.shared_fixes += is_shared_place(fix.view)
        return fix

    @property
    def shares_places(self) -> bool:
        """Whether this session's keyframes join the map live (an `extend` session's, once anchored)."""
        return self.mode == "extend" and self.anchored

    def share_keyframe(self, view: MapView) -> None:
        """Offer keyframe `view` (its pose in the map's world) to the other sessions in the map."""
        place = describe_view(view, self.localizer.extractor, self.localizer.recognizer.vocabulary,
                              self.localizer.settings.min_inliers)
        if place is not None:
            with self._lock:
                self._outgoing.append({"keyframe": int(view.id), "pose": place.pose, "places": place_arrays(place)})

    def take_outgoing(self) -> list[dict[str, Any]]:
        """The places offered since the last call."""
        with self._lock:
            out, self._outgoing = self._outgoing, []
        return out

    def add_shared(self, entries: list[dict[str, Any]]) -> None:
        """Places other sessions in the map offered (`share_keyframe`'s entries): frames are looked up among them
        too from now on."""
        localizer = self.localizer
        for entry in entries:
            try:
                place = place_from_arrays(SHARED_PLACE_IDS + self.shared_received + 1, entry["pose"],
                                          entry["places"])
                if place.points.shape != (len(place.keypoints), 3) or place.pose.shape != (4, 4):
                    raise ValueError("inconsistent shapes")
            except (KeyError, TypeError, ValueError) as err:  # a malformed entry is skipped, never fatal
                log.warning("map %s: a shared place was skipped (%s)", self.map_id, err)
                continue
            self.shared_received += 1
            localizer.add_place(place)

    def world_refinement(self, fix: MapFix, node: np.ndarray, scene_depth: float) -> np.ndarray | None:
        """A device-posed session: the correction of its world transform that its keyframes' fixes agree on, once
        WORLD_REFINE_FIXES of them are in (rotations averaged, the median translation); None until then, or when
        it is too small to matter (below WORLD_REFINE_MIN of the scene's depth and WORLD_REFINE_MIN_DEG)."""
        rigid = np.asarray(node, np.float64).copy()
        rigid[:3, :3] /= np.cbrt(np.linalg.det(rigid[:3, :3]))
        self._offsets.append(fix.pose @ np.linalg.inv(rigid))
        if len(self._offsets) < WORLD_REFINE_FIXES:
            return None
        offsets, self._offsets = np.stack(self._offsets), []
        U, _, Vt = np.linalg.svd(offsets[:, :3, :3].sum(axis=0))
        rotation = U @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))]) @ Vt
        correction = np.eye(4)
        correction[:3, :3], correction[:3, 3] = rotation, np.median(offsets[:, :3, 3], axis=0)
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))
        if np.linalg.norm(correction[:3, 3]) < WORLD_REFINE_MIN * scene_depth and angle < WORLD_REFINE_MIN_DEG:
            return None
        return correction

    def prior_sigmas(self, scene_depth: float) -> EdgeSigmas:
        """How firmly a keyframe's fix holds it (translation in pose units: a share of the scene's depth)."""
        return EdgeSigmas(PRIOR_ROTATION, PRIOR_TRANSLATION * scene_depth, PRIOR_LOG_SCALE)

    def stats(self) -> dict[str, Any]:
        return {"map_id": self.map_id, "map_version": self.version, "map_mode": self.mode,
                "map_relocalized": self.anchored, "map_fixes": self.fixes, "map_misses": self.misses,
                "map_shared_places": self.shared_received, "map_shared_fixes": self.shared_fixes,
                "map_load_seconds": self.load_seconds}

    def state_dict(self) -> dict[str, Any]:
        return {"map_id": self.map_id, "version": self.version, "mode": self.mode, "metric": self.metric,
                "anchoring": self.anchoring.state_dict(), "fixes": self.fixes, "misses": self.misses,
                "shared_fixes": self.shared_fixes,
                "relocalized_at": self.relocalized_at}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.anchoring.load_state_dict(state["anchoring"])
        self.fixes, self.misses = int(state.get("fixes", 0)), int(state.get("misses", 0))
        self.shared_fixes = int(state.get("shared_fixes", 0))
        at = state.get("relocalized_at")
        self.relocalized_at = None if at is None else int(at)


def is_shared_place(view: int) -> bool:
    """Whether a fix's view is a place another session in the map shared (not one of the saved map's keyframes)."""
    return int(view) > SHARED_PLACE_IDS


def prior_pose(fix_pose: np.ndarray, node: np.ndarray) -> np.ndarray:
    """A fix as a node's prior: the fix's rotation and position with the node's current scale."""
    scale = float(np.cbrt(np.linalg.det(node[:3, :3])))
    out = np.asarray(fix_pose, np.float64).copy()
    out[:3, :3] *= scale
    return out
