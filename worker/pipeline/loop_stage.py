"""The loop-closing stage (paper 4.2, ORB-SLAM's LoopClosing in our terms): keyframes in, pose corrections out.

It owns the keyframe pose graph, the loop closer (detection + relocalization) and the keyframe points used to
verify loops, and works in its own thread on its inputs, in order: `GraphKeyframe` (a new keyframe's node
and odometry edge, from tracking), `PosePrior` (a device's pose of that keyframe, from seeded tracking) and
`LoopQuery` (a keyframe's image and depth, from tracking when the frames carry depth, from mapping once it has
built a keyframe's multi-view depth). A verified loop adds its edges and re-optimises the graph; the optimised
keyframe poses go out as a `LoopCorrection` that the tracking thread takes with `take_corrections()` and
publishes as a new trajectory revision: tracking never waits for loop closure.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
import torch

from protocol.codec import pack
from worker.config import LoopConfig
from worker.events import DriftCorrected, EngineEvent, LoopClosed, MapsMerged, Relocalized, event_from_dict
from worker.geometry import Intrinsics, se3_part
from worker.loop.correction_check import implausible_correction
from worker.loop.keyframe_alignment import KeyframeAlignment
from worker.loop.pose_graph import PosePrior, Sim3PoseGraph
from worker.maps.localizer import MapView
from worker.maps.session_in_map import MapQuery, SessionInMap, is_shared_place, prior_pose
from worker.pipeline.loop_closer import DepthKeyframePoints, LoopCloser
from worker.pipeline.stage_thread import QueuedStage, StageThread
from worker.pipeline.stage_times import StageTimes

log = logging.getLogger(__name__)


@dataclass
class GraphKeyframe:
    """A new keyframe for the pose graph: its world pose and, after the first, the odometry edge to the previous."""

    kf_id: int
    world_pose: np.ndarray
    previous: int | None = None
    relative: np.ndarray | None = None  # previous^-1 @ this, as tracked
    kind: str = "sequential"
    scene_depth: float | None = None  # the scene's median depth known when it was made (pose units), if any
    corrections_seen: int = 0  # corrections tracking had applied when it made the node (see `_in_current_world`)


@dataclass
class LoopQuery:
    """A keyframe to detect loops with: image [1,3,H,W] in [0,1], its camera, its depth when it has one."""

    kf_id: int
    image: torch.Tensor
    intrinsics: Intrinsics | None
    depth: torch.Tensor | None = None
    K: torch.Tensor | None = None  # the depth's camera matrix


@dataclass
class MapJoin:
    """A restarted monocular map recognised a keyframe of an older one: the Sim(3) edge between keyframe `i` (the
    older map) and keyframe `j` (the new map), `relative` = T_i^-1 T_j with the new map's scale in it, and the
    tracking event that measured it."""

    i: int
    j: int
    relative: np.ndarray
    event: MapsMerged


@dataclass
class CameraUpdate:
    """The session's camera was re-estimated: keyframe points are made again with camera matrix K."""

    K: torch.Tensor


@dataclass
class LoopCorrection:
    """Optimised keyframe poses after a loop closure, and the loop's event (without the revision, which the
    trajectory gives when the correction is applied)."""

    poses: dict[int, np.ndarray]
    event: EngineEvent
    world_move: np.ndarray | None = None  # the whole world moved by it (a stored map's anchoring): frames before
    # the first keyframe move too


# What the stage takes, in order
LoopItem = GraphKeyframe | LoopQuery | CameraUpdate | PosePrior | MapJoin | MapQuery
# A session in a stored map solves its graph after this many keyframes were fixed in the map.
MAP_PRIORS_PER_SOLVE = 1
# ... and holds its first keyframe only this loosely (tangent space): the first fix's error is not kept forever
MAP_GAUGE_SIGMA = 1.0
# ICP of two keyframes' depth for metric loops: relative pose refined, or None when they do not fit.
# It pairs points closer than this many scene length units (worker.geometry.scene_units; ICL, 1.85 m: 4.6 cm).
ICP_REACH = 0.025
DepthAligner = Callable[[int, int, np.ndarray, Intrinsics | None], np.ndarray | None]


class LoopClosingStage(QueuedStage):
    """Pose graph + loop closer behind an input queue (see the module docstring)."""

    def __init__(self, cfg: LoopConfig, pose_graph: Sim3PoseGraph, closer: LoopCloser | None,
                 depth_points: DepthKeyframePoints | None, metric: bool, threaded: bool,
                 timings: StageTimes | None = None, solve_priors_every: int = 0,
                 alignment: KeyframeAlignment | None = None) -> None:
        self.cfg = cfg
        # > 0: the graph is solved after this many device priors (a monocular odometry's drift corrected between
        # loops: `drift_corrected`); 0: priors wait for the next loop
        self.solve_priors_every = solve_priors_every
        self.priors_unsolved = 0
        self.pose_graph = pose_graph
        self.closer = closer
        self.depth_points = depth_points
        self.alignment = alignment  # sensor depth, metric poses: dense edges from each keyframe to older ones near it
        self.metric = metric  # given metric poses and depth: a loop measures no scale change
        self.timings = timings or StageTimes()
        self.loops = 0
        self.solves_given_up = 0  # solves that failed or ended implausibly: nothing moved
        self._corrections: list[LoopCorrection] = []
        self._corrections_lock = threading.Lock()
        self.corrections_made = 0
        # The stored map the session runs in (worker.maps), set by assembly; its anchoring moves the whole graph
        # into the map's world: (the number of the correction that did it, the similarity) for each such move
        self.in_map: SessionInMap | None = None
        self.world_moves: list[tuple[int, np.ndarray]] = []
        self.map_priors_unsolved = 0
        self.shared_priors_unsolved = 0  # of those, fixes among other sessions' shared places
        self.name = "loop-closing"
        self._init_queue()
        self._stage = StageThread("loop-closing", self._handle_numbered, threaded)

    def take_corrections(self) -> list[LoopCorrection]:
        """The corrections made since the last call, oldest first."""
        with self._corrections_lock:
            out, self._corrections = self._corrections, []
        return out

    # -- work (the stage's thread) -------------------------------------------------------------------------------
    def _process(self, item: LoopItem) -> None:
        with self.lock:  # a snapshot (`snapshot_now`) sees the state between two items
            try:
                self._process_one(item)
            finally:
                self._done(item)

    def _process_one(self, item: LoopItem) -> None:
        try:
            self._process_item(item)
        except ValueError as error:  # a degenerate node or edge (non-finite, a scale near 0): left out, not fatal
            log.warning("loop-closing stage: %s for %s: left out of the pose graph", error, type(item).__name__)
        except RuntimeError as error:  # gtsam's IndeterminateSystemException: this item's solve is given up
            if "Indeterminate" not in str(error):
                raise
            log.warning("loop-closing stage: the pose graph could not be solved with %s: left out",
                        type(item).__name__)

    def _process_item(self, item: LoopItem) -> None:
        if isinstance(item, MapQuery):
            self._locate_in_map(item)
            return
        if isinstance(item, MapJoin):
            self._join_maps(item)
            return
        if isinstance(item, PosePrior):  # a device's pose of a keyframe (seeded tracking), after its node
            if item.key in self.pose_graph.nodes:  # in the device's world, which a map's anchoring moved
                self.pose_graph.add_prior(item.key, self._world_transform() @ item.pose, item.sigmas)
                self.pose_graph.flush()
                self.priors_unsolved += 1
                if self.solve_priors_every and self.priors_unsolved >= self.solve_priors_every:
                    self._correct_drift(item.key)
            return
        if isinstance(item, CameraUpdate):
            if self.depth_points is not None:
                self.depth_points.reproject(item.K)
            if self.alignment is not None:
                self.alignment.reproject(np.asarray(item.K, np.float64))
            return
        if isinstance(item, GraphKeyframe):
            if self.pose_graph.length_unit is None:  # the first scene depth known is the graph's length unit
                self.pose_graph.set_length_unit(item.scene_depth)
            self.pose_graph.add_node(item.kf_id, self._in_current_world(item.world_pose, item.corrections_seen))
            if item.previous is not None:
                self.pose_graph.add_edge(item.previous, item.kf_id, item.relative, kind=item.kind)
            self.pose_graph.flush()  # iSAM2 takes the keyframe now: a later loop's solve has less to do
            return
        if self.alignment is not None and item.depth is not None:
            self._align_to_neighbours(item)
        if self.closer is None:
            return
        if item.depth is not None and self.depth_points is not None:
            self.depth_points.add(item.kf_id, item.depth, item.K)
        self._close_loop(item)

    def _align_to_neighbours(self, query: LoopQuery) -> None:
        """Add the keyframe's dense edges to the older keyframes near it and solve (`drift_corrected`)."""
        if query.kf_id not in self.pose_graph.nodes:
            return
        grey = cv2.cvtColor(np.ascontiguousarray((query.image[0].permute(1, 2, 0).numpy() * 255.0).round()
                                                 .clip(0, 255).astype(np.uint8)), cv2.COLOR_RGB2GRAY)
        self.alignment.add(query.kf_id, grey, query.depth.numpy(), np.asarray(query.K, np.float64))
        linked = {edge.i for edge in self.pose_graph.edges if edge.j == query.kf_id}
        with self.timings.measure("keyframe_alignment"):
            edges = self.alignment.edges(query.kf_id, dict(self.pose_graph.nodes), self.pose_graph.length_unit or 1.0,
                                         skip=linked)
        if not edges:
            return
        before = self.pose_graph.state_dict()
        for edge in edges:
            self.pose_graph.add_edge(edge.i, edge.j, edge.relative, kind="covisible")
        self._solve(DriftCorrected(keyframe=int(query.kf_id), source="covisibility"), before)

    def _close_loop(self, query: LoopQuery) -> None:
        constraints = self.closer.process_keyframe(query.kf_id, query.image, query.intrinsics)
        kept = []
        before = None
        for constraint in constraints:
            relative = constraint.relative
            if self.metric:
                relative = self._align_depth(constraint.i, constraint.j, se3_part(relative), query.intrinsics)
                if relative is None:
                    continue
            before = before or self.pose_graph.state_dict()
            self.pose_graph.add_edge(constraint.i, constraint.j, relative, kind="loop", weight=self.cfg.loop_weight)
            kept.append(constraint)
        if not kept:
            return
        best = kept[0]
        event = LoopClosed(from_keyframe=int(best.j), to_keyframe=int(best.i), source=best.source,
                           scale=float(best.scale), also_to_keyframes=[int(c.i) for c in kept[1:]] or None)
        if self._solve(event, before):
            self.loops += 1

    def _correct_drift(self, key: int) -> None:
        """Solve the graph with the device priors so far and hand the moved keyframes back (`drift_corrected`)."""
        self.priors_unsolved = 0
        self._solve(DriftCorrected(keyframe=int(key)), self.pose_graph.state_dict())

    def _solve(self, event: EngineEvent, before: dict[str, Any]) -> bool:
        """Optimise the graph and hand the optimised keyframe poses back with `event` (and the solve's costs). A
        solve that fails or ends implausibly (worker.loop.correction_check) moves nothing: the graph goes back to
        `before` (its state before this item's edges) and the loop is given up. Returns whether it was applied."""
        try:
            with self.timings.measure("pgo"):
                result = self.pose_graph.optimize(max_iterations=self.cfg.pgo_iterations)
        except RuntimeError:
            self.pose_graph.load_state_dict(before)
            raise
        old = dict(zip(np.asarray(before["keys"]).tolist(), np.asarray(before["poses"])))
        problem = implausible_correction(old, result.poses, self.metric)
        if problem is not None:
            log.warning("loop-closing stage: %s: the %s is given up", problem, event.TYPE)
            self.pose_graph.load_state_dict(before)
            self.solves_given_up += 1
            return False
        event = replace(event, pgo_error_before=result.initial_error, pgo_error_after=result.final_error)
        self._hand_back(LoopCorrection(dict(result.poses), event))
        return True

    def _hand_back(self, correction: LoopCorrection) -> None:
        with self._corrections_lock:
            self._corrections.append(correction)
            self.corrections_made += 1

    # -- a stored map (worker.maps) ------------------------------------------------------------------------------
    def _locate_in_map(self, query: MapQuery) -> None:
        """Find the frame in the stored map: before the session is anchored, a fix counts towards the anchoring,
        which moves the whole session into the map's world once fixes agree; after, a keyframe's fix is a prior
        on its node (solved every few). A frame query with a newer one waiting is shed (it would only be late)."""
        in_map = self.in_map
        if in_map is None or (not query.keyframe and self._newer_map_query_waiting(query)):
            return
        if in_map.anchored and (not query.keyframe or query.frame not in self.pose_graph.nodes):
            return
        with self.timings.measure("map_relocalization"):
            fix = in_map.locate(query)
        if in_map.shares_places and query.keyframe and query.depth is not None:
            pose = self.pose_graph.nodes[query.frame]  # in the map's world now
            in_map.share_keyframe(MapView(query.frame, pose, query.K, query.gray, query.depth))
        if fix is None:
            return
        scene_depth = self.pose_graph.length_unit or 1.0
        if not in_map.anchored:
            own = self._in_current_world(query.own_pose, query.corrections_seen)
            scale = None if in_map.metric else in_map.depth_scale(fix, query)
            transform = in_map.anchoring.propose(query.frame, own, fix, scene_depth, scale)
            if transform is not None:
                in_map.relocalized_at = query.frame
                self._move_world(transform, Relocalized(map_id=in_map.map_id, frame=query.frame, **fix.quality()))
            return
        node = self.pose_graph.nodes[query.frame]
        if in_map.device_poses:  # the device's world is tied rigidly to the map's: refine that one transform
            correction = in_map.world_refinement(fix, node, scene_depth)
            if correction is not None:
                self._move_world(correction, DriftCorrected(keyframe=int(query.frame), source="map"))
            return
        self.pose_graph.add_prior(query.frame, prior_pose(fix.pose, node), in_map.prior_sigmas(scene_depth))
        self.pose_graph.flush()
        self.map_priors_unsolved += 1
        self.shared_priors_unsolved += is_shared_place(fix.view)
        if self.map_priors_unsolved >= MAP_PRIORS_PER_SOLVE:
            shared = self.shared_priors_unsolved or None
            self.map_priors_unsolved = self.shared_priors_unsolved = 0
            self._solve(DriftCorrected(keyframe=int(query.frame), source="map", from_other_sessions=shared),
                        self.pose_graph.state_dict())

    def _newer_map_query_waiting(self, query: MapQuery) -> bool:
        with self._unfinished_lock:
            return any(isinstance(item, MapQuery) and item.frame > query.frame for _, item in self._unfinished)

    def _move_world(self, transform: np.ndarray, event: EngineEvent) -> None:
        """Express the session in another world (the stored map's): every node moves by `transform`; tracking
        takes the moved keyframes as a correction, and nodes or queries it made before taking it are moved here
        as they come (`_in_current_world`)."""
        self.pose_graph.move_world(transform)
        self.pose_graph.loosen_gauge(MAP_GAUGE_SIGMA)  # the map's priors hold the graph: its first node too
        self._hand_back(LoopCorrection(dict(self.pose_graph.nodes), event, np.asarray(transform, np.float64)))
        self.world_moves.append((self.corrections_made, np.asarray(transform, np.float64)))

    def _in_current_world(self, pose: np.ndarray, corrections_seen: int) -> np.ndarray:
        """`pose`, made by tracking after it had applied `corrections_seen` corrections, in the graph's world now."""
        out = np.asarray(pose, np.float64)
        for number, transform in self.world_moves:
            if corrections_seen < number:
                out = transform @ out
        return out

    def _world_transform(self) -> np.ndarray:
        """Every world move so far, composed (the tracking world's first frame -> the graph's world)."""
        out = np.eye(4)
        for _, transform in self.world_moves:
            out = transform @ out
        return out

    def _join_maps(self, join: MapJoin) -> None:
        """Add the Sim(3) edge joining two maps, solve, and hand the moved keyframes back (`maps_merged`)."""
        if join.i not in self.pose_graph.nodes or join.j not in self.pose_graph.nodes or join.i == join.j:
            return
        before = self.pose_graph.state_dict()
        self.pose_graph.add_edge(join.i, join.j, join.relative, kind="map_join")
        self._solve(replace(join.event, relative=None, correction=None, from_keyframe=int(join.j),
                            to_keyframe=int(join.i)), before)

    def _align_depth(self, i: int, j: int, relative: np.ndarray, intrinsics: Intrinsics | None) -> np.ndarray | None:
        """A metric loop edge refined by ICP on the two keyframes' depth (half resolution), or None when the depth
        maps do not fit together (too few close points or a large residual)."""
        if not self.cfg.depth_alignment or intrinsics is None:
            return relative
        from worker.pipeline.rgbd_align import refine_relative_pose

        points_i, _ = self.depth_points.keyframe_points(i)
        points_j, _ = self.depth_points.keyframe_points(j)
        half = intrinsics.scaled(intrinsics.width // 2, intrinsics.height // 2).matrix()
        unit = self.pose_graph.length_unit or 1.0
        with self.timings.measure("loop_relocalization"):
            fit = refine_relative_pose(points_i[::2, ::2], points_j[::2, ::2], half, torch.from_numpy(relative),
                                       max_distance=ICP_REACH * unit)
        if fit.inlier_fraction < self.cfg.alignment_min_inliers or fit.rms > self.cfg.alignment_max_rms * unit:
            self.closer.rejected += 1
            return None
        return fit.relative.numpy()

    # -- snapshot ------------------------------------------------------------------------------------------------
    def snapshot_now(self, deliver: Callable[[Callable[[], bytes]], None],  # type: ignore[override]
                     external: dict[str, bytes] | None = None) -> None:
        """The stage's state as of now, packed, handed to `deliver(make_part)` without waiting for its queue
        (QueuedStage.snapshot_now): the graph between two items, the items not done yet and the corrections
        tracking has not taken yet, as data; a restored stage works through them (`load_state_dict`)."""
        def pack_state(items: list[Any]) -> bytes:
            with self._corrections_lock:
                corrections = [{"poses": [[k, v] for k, v in c.poses.items()], "event": c.event.to_dict(),
                                "world_move": c.world_move} for c in self._corrections]
            return pack({**self.state_dict(), "queued": [item_state(item) for item in items],
                         "corrections": corrections}, external=external)

        super().snapshot_now(deliver, pack_state)

    def state_dict(self) -> dict[str, Any]:
        """The stage's state between two work items (call it from `at_marker`, or when idle)."""
        return {"pose_graph": self.pose_graph.state_dict(),
                "loop": None if self.closer is None else self.closer.state_dict(),
                "depth_points": None if self.depth_points is None else self.depth_points.state_dict(),
                "alignment": None if self.alignment is None else self.alignment.state_dict(),
                "loops": self.loops, "priors_unsolved": self.priors_unsolved,
                "corrections_made": self.corrections_made,
                "world_moves": [[number, transform] for number, transform in self.world_moves],
                "in_map": None if self.in_map is None else self.in_map.state_dict(),
                "map_priors_unsolved": self.map_priors_unsolved,
                "shared_priors_unsolved": self.shared_priors_unsolved}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pose_graph.load_state_dict(state["pose_graph"])
        if self.closer is not None and state.get("loop") is not None:
            self.closer.load_state_dict(state["loop"])
        if self.depth_points is not None and state.get("depth_points") is not None:
            self.depth_points.load_state_dict(state["depth_points"])
        if self.alignment is not None and state.get("alignment") is not None:
            self.alignment.load_state_dict(state["alignment"])
        self.loops = int(state.get("loops", 0))
        self.priors_unsolved = int(state.get("priors_unsolved", 0))
        self.corrections_made = int(state.get("corrections_made", 0))
        self.world_moves = [(int(n), np.asarray(t, np.float64)) for n, t in state.get("world_moves") or []]
        self.map_priors_unsolved = int(state.get("map_priors_unsolved", 0))
        self.shared_priors_unsolved = int(state.get("shared_priors_unsolved", 0))
        if self.in_map is not None and state.get("in_map") is not None:
            self.in_map.load_state_dict(state["in_map"])
        with self._corrections_lock:
            self._corrections = [LoopCorrection({int(k): np.asarray(v, np.float64) for k, v in c["poses"]},
                                                event_from_dict(c["event"]),
                                                None if c.get("world_move") is None
                                                else np.asarray(c["world_move"], np.float64))
                                 for c in state.get("corrections") or []]
        for item in state.get("queued") or []:  # submitted before the snapshot, not done in it: done now
            self.submit(item_from_state(item))


def item_state(item: LoopItem) -> dict[str, Any]:
    """A work item as plain data (arrays stay arrays)."""
    if isinstance(item, GraphKeyframe):
        return {"kind": "keyframe", "kf_id": item.kf_id, "world_pose": item.world_pose, "previous": item.previous,
                "relative": item.relative, "edge": item.kind, "scene_depth": item.scene_depth,
                "corrections_seen": item.corrections_seen}
    if isinstance(item, MapQuery):
        return item.state()
    if isinstance(item, LoopQuery):
        return {"kind": "query", "kf_id": item.kf_id, "image": item.image, "depth": item.depth, "K": item.K,
                "intrinsics": None if item.intrinsics is None else item.intrinsics.to_dict()}
    if isinstance(item, MapJoin):
        return {"kind": "join", "i": item.i, "j": item.j, "relative": item.relative, "event": item.event.to_dict()}
    if isinstance(item, CameraUpdate):
        return {"kind": "camera", "K": item.K}
    return {"kind": "prior", **item.to_dict()}


def item_from_state(state: dict[str, Any]) -> LoopItem:
    def tensor(value: Any) -> torch.Tensor | None:
        return None if value is None else torch.from_numpy(np.array(value))

    def array(value: Any) -> np.ndarray | None:
        return None if value is None else np.asarray(value, np.float64)

    kind = state["kind"]
    if kind == "keyframe":
        return GraphKeyframe(int(state["kf_id"]), array(state["world_pose"]), state["previous"],
                             array(state["relative"]), state["edge"], state["scene_depth"],
                             int(state.get("corrections_seen", 0)))
    if kind == "map_query":
        return MapQuery.from_state(state)
    if kind == "query":
        intrinsics = None if state["intrinsics"] is None else Intrinsics.from_dict(state["intrinsics"])
        return LoopQuery(int(state["kf_id"]), tensor(state["image"]), intrinsics, tensor(state["depth"]),
                         tensor(state["K"]))
    if kind == "join":
        return MapJoin(int(state["i"]), int(state["j"]), array(state["relative"]), event_from_dict(state["event"]))
    if kind == "camera":
        return CameraUpdate(tensor(state["K"]))
    return PosePrior.from_dict(state)
