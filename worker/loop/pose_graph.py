"""Sim(3) pose graph over keyframe poses (paper eq. 14), solved incrementally with GTSAM's iSAM2.

Nodes are keyframe camera-to-world similarities T_k^W. An edge (i, j) carries the measured relative similarity
H = T_i^-1 T_j (the pose of j in the frame of i) and penalises log(H^-1 T_i^-1 T_j) in sim(3) with a diagonal
information matrix. GTSAM solves in the scene's length unit (`length_unit`, the median depth of the first
keyframe whose depth is known: worker.geometry.scene_units): translations are divided by it on the way in and
multiplied on the way out, so that edge sigmas, the robust kernel and iSAM2's relinearisation threshold mean the
same for the same scene in metres or in millimetres. The main kinds of edges are sequential
(consecutive keyframes inside one submap), inter-submap (through the overlap frame), loop and covisible (RGB-D
keyframes aligned densely to the older ones near them; `EDGE_KINDS` lists all). Loop and covisible edges get a
robust kernel by default so a single wrong loop is down-weighted instead of bending the whole trajectory; a prior
pins the first keyframe (the gauge).
Absolute priors (`PosePrior`, e.g. a device's pose of a keyframe with its stated uncertainty) pull single nodes
towards measured world poses, through the same robust kernel as loop edges.

`optimize()` hands the nodes and edges added since the last call to iSAM2 (worker.loop.incremental), which
re-eliminates only the part of the graph they touch; `optimize_full()` is the batch Levenberg-Marquardt solve over
everything, the reference the incremental one is tested against. The first solve, and the first after a restore or
after a node was re-initialised, is a batch solve that iSAM2 then starts from.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import gtsam
import numpy as np
import torch

from worker.geometry import relative_transform, sim3_decompose
from worker.geometry.scene_units import valid_unit

from .incremental import IncrementalSolver

log = logging.getLogger(__name__)

# new_map: between a lost map and a map begun from nothing after it; restart: across the seam of a monocular map
# restarted from the last tracked frame after a loss (its scale is a guess); map_join: the Sim(3) that joins such a
# map to an older one where it recognised an older keyframe.
# covisible: between RGB-D keyframes that see the same surfaces, measured by dense alignment
# (worker.loop.keyframe_alignment).
EDGE_KINDS = ("sequential", "inter_submap", "loop", "new_map", "restart", "map_join", "covisible")
DIVERGED_COST_RATIO = 1.05  # an incremental solve ending this much above its starting cost is redone in batch


@dataclass(frozen=True)
class EdgeSigmas:
    """Standard deviations of one edge kind in sim(3) tangent space: rotation (rad), translation (scene length
    units for edges, pose units for priors), log-scale. GTSAM orders the tangent as (rotation, translation,
    log-scale)."""

    rotation: float = 0.01
    translation: float = 0.02
    log_scale: float = 0.01

    def vector(self, weight: float = 1.0, length_unit: float = 1.0) -> np.ndarray:
        """The 7 standard deviations, the translation's in pose units (`length_unit` pose units each), for an
        information scaled by `weight`."""
        sig = np.array([self.rotation] * 3 + [self.translation * length_unit] * 3 + [self.log_scale],
                       dtype=np.float64)
        if weight <= 0:
            raise ValueError(f"edge weight must be positive, got {weight}")
        return sig / np.sqrt(weight)


# Translations in scene length units (the first keyframe's median depth): odometry edges 1 % of it, loops 2 %. They
# were 0.02 and 0.04 pose units: in metres, 1.1 and 2.2 % of ICL's scene (first keyframe at 1.85 m), which keeps its
# weights; in visual odometry's units (first keyframe at 1) 2 and 4 %, yet ICL RGB only measured the same with 1 and
# 2 % (1.82 cm / 28.13 dB against 1.84 / 28.11; bench/RESULTS.md, "The map does not depend on the scene's units").
DEFAULT_SIGMAS: dict[str, EdgeSigmas] = {
    "sequential": EdgeSigmas(0.01, 0.01, 0.01),
    "inter_submap": EdgeSigmas(0.01, 0.01, 0.01),
    "loop": EdgeSigmas(0.02, 0.02, 0.02),
    "covisible": EdgeSigmas(0.01, 0.01, 0.01),  # the alignment odometry's own edges come from: as certain
    # Between the last keyframe of a lost map and the first of the map begun after it: the new map was only placed
    # at the last pose with the old scene depth, so the edge holds it there until a loop gives the true Sim(3).
    "new_map": EdgeSigmas(1.0, 10.0, 1.0),
    "restart": EdgeSigmas(0.02, 0.5, 1.0),
    "map_join": EdgeSigmas(0.02, 0.04, 0.02),
}


@dataclass(frozen=True)
class PoseGraphEdge:
    """A relative Sim(3) constraint: `relative` = T_i^-1 T_j, with information scaled by `weight`."""

    i: int
    j: int
    relative: np.ndarray
    kind: str = "sequential"
    weight: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in EDGE_KINDS:
            raise ValueError(f"edge kind must be one of {EDGE_KINDS}, got {self.kind!r}")
        if self.i == self.j:
            raise ValueError(f"an edge needs two different nodes, got ({self.i}, {self.j})")
        if np.asarray(self.relative).shape != (4, 4):
            raise ValueError(f"edge relative pose must be 4x4, got {np.asarray(self.relative).shape}")

    def to_dict(self) -> dict:
        return {"i": self.i, "j": self.j, "relative": np.asarray(self.relative, np.float64), "kind": self.kind,
                "weight": self.weight}

    @classmethod
    def from_dict(cls, d: Mapping) -> PoseGraphEdge:
        return cls(int(d["i"]), int(d["j"]), np.asarray(d["relative"], np.float64), str(d["kind"]), float(d["weight"]))


@dataclass(frozen=True)
class PosePrior:
    """An absolute measurement of node `key`'s world pose (4x4 c2w) with standard deviations `sigmas`."""

    key: int
    pose: np.ndarray
    sigmas: EdgeSigmas

    def to_dict(self) -> dict:
        s = self.sigmas
        return {"key": self.key, "pose": np.asarray(self.pose, np.float64),
                "sigmas": [s.rotation, s.translation, s.log_scale]}

    @classmethod
    def from_dict(cls, d: Mapping) -> PosePrior:
        return cls(int(d["key"]), np.asarray(d["pose"], np.float64), EdgeSigmas(*(float(v) for v in d["sigmas"])))


@dataclass
class PoseGraphResult:
    """Optimised poses by key, with the cost before/after, LM iterations (iSAM2 updates for an incremental
    solve) and which solve ran ("batch" or "incremental")."""

    poses: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int
    loop_residuals: dict[tuple[int, int], float] = field(default_factory=dict)
    solver: str = "batch"


def sim3_batch_to_gtsam(T: np.ndarray) -> list[gtsam.Similarity3]:
    """[N,4,4] similarities as gtsam.Similarity3 (batched form of gtsam_bridge.sim3_to_gtsam: t_gtsam = t / s)."""
    s, R, t = sim3_decompose(torch.as_tensor(np.asarray(T), dtype=torch.float64))
    t_g = (t / s[:, None]).numpy()
    return [gtsam.Similarity3(gtsam.Rot3(R[n].numpy()), t_g[n], float(s[n])) for n in range(len(s))]


def sim3_batch_from_gtsam(values: list[gtsam.Similarity3]) -> np.ndarray:
    """gtsam.Similarity3 list as [N,4,4] (batched gtsam_bridge.sim3_from_gtsam: GTSAM's matrix is [R t; 0 1/s])."""
    out = np.zeros((len(values), 4, 4))
    if not values:
        return out
    M = np.stack([v.matrix() for v in values])
    s = 1.0 / M[:, 3, 3]
    out[:, :3, :3] = s[:, None, None] * M[:, :3, :3]
    out[:, :3, 3] = M[:, :3, 3] * s[:, None]
    out[:, 3, 3] = 1.0
    return out


MIN_SCALE, MAX_SCALE = 1e-6, 1e6  # a Sim(3) scale outside these leaves the solve indeterminate


def _as_matrix(T: np.ndarray | torch.Tensor) -> np.ndarray:
    """A 4x4 float64 Sim(3), finite and of a usable scale (ValueError otherwise: such a pose or measurement would
    make every later solve of the graph fail)."""
    M = T.detach().cpu().numpy() if isinstance(T, torch.Tensor) else np.asarray(T)
    if M.shape != (4, 4):
        raise ValueError(f"poses must be 4x4, got {M.shape}")
    M = M.astype(np.float64)
    if not np.all(np.isfinite(M)):
        raise ValueError("a pose or measurement is not finite")
    scale = float(np.cbrt(abs(np.linalg.det(M[:3, :3]))))
    if not MIN_SCALE <= scale <= MAX_SCALE:
        raise ValueError(f"a pose or measurement has scale {scale:.3g}, outside [{MIN_SCALE:g}, {MAX_SCALE:g}]")
    return M


class Sim3PoseGraph:
    """Keyframe Sim(3) pose graph: add nodes and edges, then `optimize()`.

    robust: "cauchy", "huber" or None; applied to the edge kinds in `robust_kinds` (loop and covisible edges by
    default) with threshold `robust_k` on the whitened residual norm. incremental: solve with iSAM2 after the first
    (batch) solve; False solves every time with batch Levenberg-Marquardt. relinearize_threshold: iSAM2 relinearises
    a node whose step exceeds this tangent-space norm. length_unit: pose units per scene length unit, the unit of
    the edges' translation sigmas (None: 1, until `set_length_unit`). The methods may be called from several threads
    (one lock).
    """

    def __init__(
        self,
        sigmas: Mapping[str, EdgeSigmas] | None = None,
        robust: str | None = "cauchy",
        robust_k: float = 1.0,
        robust_kinds: Iterable[str] = ("loop", "covisible"),
        prior_sigma: float = 1e-6,
        incremental: bool = True,
        relinearize_threshold: float = 0.001,
        length_unit: float | None = None,
    ) -> None:
        if robust not in ("cauchy", "huber", None):
            raise ValueError(f"robust kernel must be 'cauchy', 'huber' or None, got {robust!r}")
        if relinearize_threshold <= 0:
            raise ValueError(f"relinearize_threshold must be positive, got {relinearize_threshold}")
        self.sigmas = {**DEFAULT_SIGMAS, **(sigmas or {})}
        self.robust = robust
        self.robust_k = robust_k
        self.robust_kinds = frozenset(robust_kinds)
        self.prior_sigma = prior_sigma
        self.gauge_sigma: float | None = None  # set: the first node is held only this loosely (`loosen_gauge`)
        self.incremental = incremental
        self.relinearize_threshold = relinearize_threshold
        self.length_unit = valid_unit(length_unit)  # pose units per scene length unit; None: not known yet (1)
        self.nodes: dict[int, np.ndarray] = {}
        self.edges: list[PoseGraphEdge] = []
        self.priors: list[PosePrior] = []
        self._lock = threading.RLock()
        self._noises = {kind: self._noise_model(kind) for kind in EDGE_KINDS}
        self._drop_solver()

    def __len__(self) -> int:
        return len(self.nodes)

    def set_length_unit(self, unit: float | None) -> None:
        """Measure edge translations in units of `unit` pose units (the scene's median depth); None or an invalid
        value: 1. A change re-weighs every edge, so the next solve is a batch one."""
        unit = valid_unit(unit)
        with self._lock:
            if unit == self.length_unit:
                return
            self.length_unit = unit
            self._noises = {kind: self._noise_model(kind) for kind in EDGE_KINDS}
            self._drop_solver()

    def _edge_sigmas(self, kind: str, weight: float = 1.0) -> np.ndarray:
        """The standard deviations of an edge of `kind` in scene length units (GTSAM's units: `_to_gtsam`)."""
        return self.sigmas[kind].vector(weight)

    def _to_gtsam(self, T: np.ndarray) -> list[gtsam.Similarity3]:
        """[N,4,4] poses or measurements as GTSAM sees them: translations in scene length units, so that the
        solve (iSAM2's relinearisation threshold, its convergence) is the same in any pose units."""
        T = np.array(T, np.float64)
        if self.length_unit is not None:
            T[:, :3, 3] /= self.length_unit
        return sim3_batch_to_gtsam(T)

    def _from_gtsam(self, values: list[gtsam.Similarity3]) -> np.ndarray:
        """GTSAM's similarities back in pose units, [N,4,4]."""
        T = sim3_batch_from_gtsam(values)
        if self.length_unit is not None:
            T[:, :3, 3] *= self.length_unit
        return T

    def add_node(self, key: int, pose: np.ndarray | torch.Tensor) -> None:
        """Add (or re-initialise) keyframe `key` with its current world pose (4x4 Sim(3) c2w)."""
        key = int(key)
        with self._lock:
            self.nodes[key] = _as_matrix(pose)
            if self._solver is None:
                return
            if key in self._solver or key < self._anchor:
                self._drop_solver()  # a moved linearisation point or a new gauge: the next solve starts afresh
            else:
                self._pending[key] = None

    def add_edge(self, i: int, j: int, relative: np.ndarray | torch.Tensor, kind: str = "sequential",
                 weight: float = 1.0) -> PoseGraphEdge:
        """Constrain T_i^-1 T_j = relative. Both nodes must exist."""
        with self._lock:
            for key in (i, j):
                if int(key) not in self.nodes:
                    raise ValueError(f"pose graph has no node {key}")
            edge = PoseGraphEdge(int(i), int(j), _as_matrix(relative), kind, float(weight))
            self.edges.append(edge)
            return edge

    def add_odometry_edge(self, i: int, j: int, kind: str = "sequential", weight: float = 1.0) -> PoseGraphEdge:
        """An edge whose measurement is the current relative pose of the two nodes (sequential/inter-submap)."""
        rel = relative_transform(torch.from_numpy(self.nodes[int(i)]), torch.from_numpy(self.nodes[int(j)]))
        return self.add_edge(i, j, rel, kind, weight)

    def add_prior(self, key: int, pose: np.ndarray | torch.Tensor, sigmas: EdgeSigmas) -> PosePrior:
        """Measure node `key`'s world pose directly (an absolute prior with standard deviations `sigmas`)."""
        with self._lock:
            if int(key) not in self.nodes:
                raise ValueError(f"pose graph has no node {key}")
            prior = PosePrior(int(key), _as_matrix(pose), sigmas)
            if not np.all(np.isfinite(prior.pose)):
                raise ValueError(f"prior on node {key} is not finite")
            self.priors.append(prior)
            return prior

    def loosen_gauge(self, sigma: float) -> None:
        """Hold the first node only loosely (`sigma` in its tangent space) from now on: for a graph whose world its
        absolute priors fix (a session anchored in a stored map), so that they may move the first node too. The next
        solve is a batch one."""
        with self._lock:
            self.gauge_sigma = float(sigma)
            self._drop_solver()

    def move_world(self, transform: np.ndarray) -> None:
        """Express the whole graph in another world: every node and prior pose left-multiplied by the similarity
        `transform` (edges, being relative, stay; the length unit follows its scale). The next solve is a batch."""
        S = _as_matrix(transform)
        scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
        if not np.all(np.isfinite(S)) or not scale > 0:
            raise ValueError("a world move must be a finite similarity")
        with self._lock:
            self.nodes = {k: S @ v for k, v in self.nodes.items()}
            self.priors = [PosePrior(p.key, S @ p.pose, p.sigmas) for p in self.priors]
            if self.length_unit is not None:
                self.length_unit = valid_unit(self.length_unit * scale)
                self._noises = {kind: self._noise_model(kind) for kind in EDGE_KINDS}
            self._drop_solver()

    def edges_of_kind(self, kind: str) -> list[PoseGraphEdge]:
        return [e for e in self.edges if e.kind == kind]

    def _noise_model(self, kind: str, weight: float = 1.0) -> gtsam.noiseModel.Base:
        base = gtsam.noiseModel.Diagonal.Sigmas(self._edge_sigmas(kind, weight))
        if self.robust is None or kind not in self.robust_kinds:
            return base
        estimator = (gtsam.noiseModel.mEstimator.Cauchy if self.robust == "cauchy"
                     else gtsam.noiseModel.mEstimator.Huber).Create(self.robust_k)
        return gtsam.noiseModel.Robust.Create(estimator, base)

    def _add_edge_factors(self, graph: gtsam.NonlinearFactorGraph, edges: list[PoseGraphEdge]) -> None:
        measured = self._to_gtsam(np.stack([e.relative for e in edges])) if edges else []
        for edge, meas in zip(edges, measured):
            noise = self._noises[edge.kind] if edge.weight == 1.0 else self._noise_model(edge.kind, edge.weight)
            graph.add(gtsam.BetweenFactorSimilarity3(edge.i, edge.j, meas, noise))

    def _add_prior_factors(self, graph: gtsam.NonlinearFactorGraph, priors: list[PosePrior]) -> None:
        measured = self._to_gtsam(np.stack([p.pose for p in priors])) if priors else []
        unit = 1.0 if self.length_unit is None else self.length_unit
        for prior, meas in zip(priors, measured):  # a prior's translation sigma is in pose units
            noise = gtsam.noiseModel.Diagonal.Sigmas(prior.sigmas.vector(1.0, 1.0 / unit))
            if self.robust is not None:
                estimator = (gtsam.noiseModel.mEstimator.Cauchy if self.robust == "cauchy"
                             else gtsam.noiseModel.mEstimator.Huber).Create(self.robust_k)
                noise = gtsam.noiseModel.Robust.Create(estimator, noise)
            graph.add(gtsam.PriorFactorSimilarity3(prior.key, meas, noise))

    def _values(self, keys: list[int]) -> gtsam.Values:
        values = gtsam.Values()
        if keys:
            for key, pose in zip(keys, self._to_gtsam(np.stack([self.nodes[k] for k in keys]))):
                values.insert(key, pose)
        return values

    def _isolated(self, anchor: int) -> dict[int, None]:
        """Nodes that are neither the anchor nor on an edge."""
        connected = {anchor, *(e.i for e in self.edges), *(e.j for e in self.edges), *(p.key for p in self.priors)}
        return dict.fromkeys(k for k in self.nodes if k not in connected)

    def _anchor_of(self, fixed: int | None) -> int:
        if not self.nodes:
            raise ValueError("pose graph is empty")
        return min(self.nodes) if fixed is None else int(fixed)

    def build(self, fixed: int | None = None) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The GTSAM factor graph and initial values; `fixed` (default: the smallest key) gets the prior. Nodes
        without any edge (yet) are left out."""
        anchor = self._anchor_of(fixed)
        graph = gtsam.NonlinearFactorGraph()
        isolated = self._isolated(anchor)
        values = self._values([k for k in self.nodes if k not in isolated])
        prior = gtsam.noiseModel.Isotropic.Sigma(7, self.gauge_sigma or self.prior_sigma)
        graph.add(gtsam.PriorFactorSimilarity3(anchor, values.atSimilarity3(anchor), prior))
        self._add_edge_factors(graph, self.edges)
        self._add_prior_factors(graph, self.priors)
        return graph, values

    def _result(self, values: gtsam.Values, initial_error: float, final_error: float, iterations: int,
                update: bool, unsolved: Mapping[int, None] | None = None) -> PoseGraphResult:
        """The result over `values`; nodes in `unsolved` (not in `values`) keep their poses."""
        unsolved = unsolved or {}
        keys = [k for k in self.nodes if k not in unsolved]
        poses = dict(zip(keys, self._from_gtsam([values.atSimilarity3(k) for k in keys])))
        poses.update({k: self.nodes[k] for k in unsolved})
        loop_residuals = {}
        for edge in self.edges_of_kind("loop"):
            err = values.atSimilarity3(edge.i).between(values.atSimilarity3(edge.j))
            delta = gtsam.Similarity3.Logmap(self._to_gtsam(edge.relative[None])[0].between(err))
            loop_residuals[(edge.i, edge.j)] = float(np.linalg.norm(delta / self._edge_sigmas("loop", edge.weight)))
        if update:
            self.nodes.update(poses)
        return PoseGraphResult(poses, float(initial_error), float(final_error), iterations, loop_residuals)

    def optimize(self, max_iterations: int = 50, fixed: int | None = None, update: bool = True,
                 relative_tolerance: float = 1e-4) -> PoseGraphResult:
        """Solve for every node: with iSAM2 from the last solve (`incremental`, same gauge), else with
        `optimize_full`, which then seeds iSAM2. With `update`, the graph's nodes take the optimised poses.
        `iterations` counts LM iterations, or iSAM2 updates for an incremental solve."""
        with self._lock:
            anchor = self._anchor_of(fixed)
            if self.incremental and self._solver is not None and anchor == self._anchor:
                result = self._optimize_incremental(max_iterations, update)
                if result is not None:
                    return result
            graph, values, result = self._optimize_batch(anchor, max_iterations, relative_tolerance)
            isolated = self._isolated(anchor)
            if self.incremental:
                self._seed_solver(anchor, graph, values)
                self._pending = dict(isolated)
            return self._result(values, *result, update=update, unsolved=isolated)

    def optimize_full(self, max_iterations: int = 50, fixed: int | None = None, update: bool = True,
                      relative_tolerance: float = 1e-4) -> PoseGraphResult:
        """Levenberg-Marquardt over all nodes from their current poses (the reference solve; leaves iSAM2 alone)."""
        with self._lock:
            anchor = self._anchor_of(fixed)
            _, values, result = self._optimize_batch(anchor, max_iterations, relative_tolerance)
            if update:
                self._drop_solver()  # iSAM2 no longer linearises at the nodes' poses
            return self._result(values, *result, update=update, unsolved=self._isolated(anchor))

    def _optimize_batch(self, anchor: int, max_iterations: int, relative_tolerance: float
                        ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, tuple[float, float, int]]:
        graph, values = self.build(anchor)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_tolerance)
        params.setAbsoluteErrorTol(1e-9)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        initial_error = graph.error(values)
        solution = optimizer.optimize()
        return graph, solution, (initial_error, graph.error(solution), optimizer.iterations())

    def _drop_solver(self) -> None:
        self._solver: IncrementalSolver | None = None
        self._anchor: int | None = None
        self._edges_sent = 0
        self._priors_sent = 0
        self._pending: dict[int, None] = {}  # nodes added since the solver was seeded, not yet handed to it

    def _seed_solver(self, anchor: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """A fresh iSAM2 over the whole graph, linearised at `values` (a solution, so one update suffices)."""
        self._solver = IncrementalSolver(self.relinearize_threshold)
        self._solver.solve(graph, values, max_updates=1)
        self._anchor = anchor
        self._edges_sent = len(self.edges)
        self._priors_sent = len(self.priors)
        self._pending = {}

    def _new_factors(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The edges not yet in iSAM2 and the pending nodes they reach (a node without an edge would leave
        Gauss-Newton's system singular: it waits for its first edge)."""
        edges = self.edges[self._edges_sent:]
        priors = self.priors[self._priors_sent:]
        factors = gtsam.NonlinearFactorGraph()
        self._add_edge_factors(factors, edges)
        self._add_prior_factors(factors, priors)
        reached = {k for e in edges for k in (e.i, e.j) if k in self._pending} | {
            p.key for p in priors if p.key in self._pending}
        keys = [k for k in self._pending if k in reached]
        for key in keys:
            del self._pending[key]
        self._edges_sent = len(self.edges)
        self._priors_sent = len(self.priors)
        return factors, self._values(keys)

    def _optimize_incremental(self, max_iterations: int, update: bool) -> PoseGraphResult | None:
        """Fold the new nodes and edges into iSAM2 and iterate; None (and no solver) if the cost went up, so
        that the caller falls back to the batch solve."""
        solver = self._solver
        factors, values = self._new_factors()
        before = solver.estimate()
        before.insert(values)
        initial_error = solver.factors().error(before) + factors.error(before)
        try:
            step = solver.solve(factors, values, max_updates=max_iterations)
        except RuntimeError as error:
            self._give_up_incremental(error)
            return None
        estimate = solver.estimate()
        final_error = solver.factors().error(estimate)
        # Partial relinearisation may end a little above the start when the new edges agree with the estimate;
        # a clearly higher cost means Gauss-Newton diverged, and the batch solve (damped) takes over.
        if not np.isfinite(final_error) or final_error > DIVERGED_COST_RATIO * initial_error + 1e-9:
            self._drop_solver()
            return None
        result = self._result(estimate, initial_error, final_error, step.updates, update, self._pending)
        result.solver = "incremental"
        return result

    def flush(self) -> bool:
        """Hand the nodes and edges added since the last solve to iSAM2 now (one update, no result), so that the
        next `optimize` has less to do; False when there is no incremental solver yet (before the first solve)."""
        with self._lock:
            if self._solver is None:
                return False
            if len(self.edges) > self._edges_sent or len(self.priors) > self._priors_sent:
                try:
                    self._solver.solve(*self._new_factors(), max_updates=1)
                except RuntimeError as error:  # iSAM2's undamped step met an ill-posed system
                    self._give_up_incremental(error)
                    return False
            return True

    def _give_up_incremental(self, error: RuntimeError) -> None:
        """iSAM2 (Gauss-Newton, undamped) threw on a near-indeterminate system (gtsam's IndeterminateSystemException,
        raised as RuntimeError): its state is dropped and the next solve is the damped batch one, which seeds a new
        iSAM2. The graph itself is kept whole."""
        log.warning("pose graph: iSAM2 failed (%s); the batch solve takes over", str(error).strip().splitlines()[0])
        self._drop_solver()

    def state_dict(self) -> dict:
        """msgpack-able contents (nodes and edges; the solver settings are construction arguments)."""
        with self._lock:
            keys = sorted(self.nodes)
            return {"keys": np.asarray(keys, np.int64),
                    "poses": np.stack([self.nodes[k] for k in keys]) if keys else np.zeros((0, 4, 4)),
                    "edges": [e.to_dict() for e in self.edges], "priors": [p.to_dict() for p in self.priors],
                    "length_unit": self.length_unit, "gauge_sigma": self.gauge_sigma}

    def load_state_dict(self, state: Mapping) -> None:
        """Restore nodes and edges. iSAM2 is rebuilt by the next `optimize`, a batch solve that seeds it."""
        keys = np.asarray(state["keys"]).tolist()
        poses = np.asarray(state["poses"], np.float64)
        with self._lock:
            self.nodes = {int(k): poses[n] for n, k in enumerate(keys)}
            self.edges = [PoseGraphEdge.from_dict(d) for d in state["edges"]]
            self.priors = [PosePrior.from_dict(d) for d in state.get("priors", [])]
            self.length_unit = valid_unit(state.get("length_unit"))
            self.gauge_sigma = state.get("gauge_sigma")
            self._noises = {kind: self._noise_model(kind) for kind in EDGE_KINDS}
            self._drop_solver()


def propagate_to_frames(
    frame_poses: Mapping[int, np.ndarray],
    frame_keyframe: Mapping[int, int],
    old_keyframe_poses: Mapping[int, np.ndarray],
    new_keyframe_poses: Mapping[int, np.ndarray],
) -> dict[int, np.ndarray]:
    """Move every frame with its keyframe: T_f' = T_k' T_k^-1 T_f (relative pose to its keyframe kept).

    frame_keyframe maps each frame index to the keyframe it follows; frames whose keyframe was not optimised keep
    their pose.
    """
    out: dict[int, np.ndarray] = {}
    for idx, pose in frame_poses.items():
        kf = frame_keyframe.get(idx)
        if kf is None or kf not in new_keyframe_poses:
            out[idx] = np.asarray(pose, np.float64)
            continue
        old = torch.from_numpy(np.asarray(old_keyframe_poses[kf], np.float64))
        new = torch.from_numpy(np.asarray(new_keyframe_poses[kf], np.float64))
        rel = relative_transform(old, torch.from_numpy(np.asarray(pose, np.float64)))
        out[idx] = (new @ rel).numpy()
    return out
