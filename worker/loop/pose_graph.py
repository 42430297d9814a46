"""Sim(3) pose graph over keyframe poses (paper eq. 14), solved with GTSAM Levenberg-Marquardt.

Nodes are keyframe camera-to-world similarities T_k^W. An edge (i, j) carries the measured relative similarity
H = T_i^-1 T_j (the pose of j in the frame of i) and penalises log(H^-1 T_i^-1 T_j) in sim(3) with a diagonal
information matrix. Three kinds of edges exist: sequential (consecutive keyframes inside one submap),
inter-submap (through the overlap frame) and loop. Loop edges get a robust kernel by default so a single wrong
loop is down-weighted instead of bending the whole trajectory; a prior pins the first keyframe (the gauge).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import gtsam
import numpy as np
import torch

from worker.geometry import make_sim3, relative_transform, sim3_decompose
from worker.geometry.gtsam_bridge import sim3_to_gtsam

EDGE_KINDS = ("sequential", "inter_submap", "loop")


@dataclass(frozen=True)
class EdgeSigmas:
    """Standard deviations of one edge kind in sim(3) tangent space: rotation (rad), translation (map units),
    log-scale. GTSAM orders the tangent as (rotation, translation, log-scale)."""

    rotation: float = 0.01
    translation: float = 0.02
    log_scale: float = 0.01

    def vector(self, weight: float = 1.0) -> np.ndarray:
        sig = np.array([self.rotation] * 3 + [self.translation] * 3 + [self.log_scale], dtype=np.float64)
        if weight <= 0:
            raise ValueError(f"edge weight must be positive, got {weight}")
        return sig / np.sqrt(weight)


DEFAULT_SIGMAS: dict[str, EdgeSigmas] = {
    "sequential": EdgeSigmas(0.01, 0.02, 0.01),
    "inter_submap": EdgeSigmas(0.01, 0.02, 0.01),
    "loop": EdgeSigmas(0.02, 0.04, 0.02),
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


@dataclass
class PoseGraphResult:
    """Optimised poses by key, with the cost before/after and LM iterations."""

    poses: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int
    loop_residuals: dict[tuple[int, int], float] = field(default_factory=dict)


def sim3_batch_to_gtsam(T: np.ndarray) -> list[gtsam.Similarity3]:
    """[N,4,4] similarities as gtsam.Similarity3 (batched form of gtsam_bridge.sim3_to_gtsam: t_gtsam = t / s)."""
    s, R, t = sim3_decompose(torch.as_tensor(np.asarray(T), dtype=torch.float64))
    t_g = (t / s[:, None]).numpy()
    return [gtsam.Similarity3(gtsam.Rot3(R[n].numpy()), t_g[n], float(s[n])) for n in range(len(s))]


def sim3_batch_from_gtsam(values: list[gtsam.Similarity3]) -> np.ndarray:
    """gtsam.Similarity3 list as [N,4,4] (batched gtsam_bridge.sim3_from_gtsam: GTSAM's matrix is [R t; 0 1/s])."""
    if not values:
        return np.zeros((0, 4, 4))
    M = torch.from_numpy(np.stack([v.matrix() for v in values]))
    s = 1.0 / M[:, 3, 3]
    return make_sim3(M[:, :3, :3], M[:, :3, 3] * s[:, None], s).numpy()


def _as_matrix(T: np.ndarray | torch.Tensor) -> np.ndarray:
    M = T.detach().cpu().numpy() if isinstance(T, torch.Tensor) else np.asarray(T)
    if M.shape != (4, 4):
        raise ValueError(f"poses must be 4x4, got {M.shape}")
    return M.astype(np.float64)


class Sim3PoseGraph:
    """Keyframe Sim(3) pose graph: add nodes and edges, then `optimize()`.

    robust: "cauchy", "huber" or None; applied to the edge kinds in `robust_kinds` (loop edges by default) with
    threshold `robust_k` on the whitened residual norm.
    """

    def __init__(
        self,
        sigmas: Mapping[str, EdgeSigmas] | None = None,
        robust: str | None = "cauchy",
        robust_k: float = 1.0,
        robust_kinds: Iterable[str] = ("loop",),
        prior_sigma: float = 1e-6,
    ) -> None:
        if robust not in ("cauchy", "huber", None):
            raise ValueError(f"robust kernel must be 'cauchy', 'huber' or None, got {robust!r}")
        self.sigmas = {**DEFAULT_SIGMAS, **(sigmas or {})}
        self.robust = robust
        self.robust_k = robust_k
        self.robust_kinds = frozenset(robust_kinds)
        self.prior_sigma = prior_sigma
        self.nodes: dict[int, np.ndarray] = {}
        self.edges: list[PoseGraphEdge] = []

    def __len__(self) -> int:
        return len(self.nodes)

    def add_node(self, key: int, pose: np.ndarray | torch.Tensor) -> None:
        """Add (or re-initialise) keyframe `key` with its current world pose (4x4 Sim(3) c2w)."""
        self.nodes[int(key)] = _as_matrix(pose)

    def add_edge(self, i: int, j: int, relative: np.ndarray | torch.Tensor, kind: str = "sequential",
                 weight: float = 1.0) -> PoseGraphEdge:
        """Constrain T_i^-1 T_j = relative. Both nodes must exist."""
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

    def edges_of_kind(self, kind: str) -> list[PoseGraphEdge]:
        return [e for e in self.edges if e.kind == kind]

    def _noise_model(self, kind: str, weight: float = 1.0) -> gtsam.noiseModel.Base:
        base = gtsam.noiseModel.Diagonal.Sigmas(self.sigmas[kind].vector(weight))
        if self.robust is None or kind not in self.robust_kinds:
            return base
        estimator = (gtsam.noiseModel.mEstimator.Cauchy if self.robust == "cauchy"
                     else gtsam.noiseModel.mEstimator.Huber).Create(self.robust_k)
        return gtsam.noiseModel.Robust.Create(estimator, base)

    def build(self, fixed: int | None = None) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The GTSAM factor graph and initial values; `fixed` (default: the smallest key) gets the prior."""
        if not self.nodes:
            raise ValueError("pose graph is empty")
        anchor = min(self.nodes) if fixed is None else int(fixed)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        keys = list(self.nodes)
        for key, pose in zip(keys, sim3_batch_to_gtsam(np.stack([self.nodes[k] for k in keys]))):
            values.insert(key, pose)
        prior = gtsam.noiseModel.Isotropic.Sigma(7, self.prior_sigma)
        graph.add(gtsam.PriorFactorSimilarity3(anchor, values.atSimilarity3(anchor), prior))
        noises = {kind: self._noise_model(kind) for kind in EDGE_KINDS}
        measured = sim3_batch_to_gtsam(np.stack([e.relative for e in self.edges])) if self.edges else []
        for edge, meas in zip(self.edges, measured):
            noise = noises[edge.kind] if edge.weight == 1.0 else self._noise_model(edge.kind, edge.weight)
            graph.add(gtsam.BetweenFactorSimilarity3(edge.i, edge.j, meas, noise))
        return graph, values

    def optimize(self, max_iterations: int = 50, fixed: int | None = None, update: bool = True,
                 relative_tolerance: float = 1e-4) -> PoseGraphResult:
        """Levenberg-Marquardt over all nodes. With `update`, the graph's nodes take the optimised poses."""
        graph, values = self.build(fixed)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_tolerance)
        params.setAbsoluteErrorTol(1e-9)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        initial_error = graph.error(values)
        result = optimizer.optimize()
        keys = list(self.nodes)
        poses = dict(zip(keys, sim3_batch_from_gtsam([result.atSimilarity3(k) for k in keys])))
        loop_residuals = {}
        for edge in self.edges_of_kind("loop"):
            err = result.atSimilarity3(edge.i).between(result.atSimilarity3(edge.j))
            delta = gtsam.Similarity3.Logmap(sim3_to_gtsam(edge.relative).between(err))
            loop_residuals[(edge.i, edge.j)] = float(np.linalg.norm(delta / self.sigmas["loop"].vector(edge.weight)))
        if update:
            self.nodes.update(poses)
        return PoseGraphResult(poses, float(initial_error), float(graph.error(result)), optimizer.iterations(),
                               loop_residuals)

    def state_dict(self) -> dict:
        """msgpack-able contents (nodes and edges; the solver settings are construction arguments)."""
        keys = sorted(self.nodes)
        return {"keys": np.asarray(keys, np.int64),
                "poses": np.stack([self.nodes[k] for k in keys]) if keys else np.zeros((0, 4, 4)),
                "edges": [e.to_dict() for e in self.edges]}

    def load_state_dict(self, state: Mapping) -> None:
        keys = np.asarray(state["keys"]).tolist()
        poses = np.asarray(state["poses"], np.float64)
        self.nodes = {int(k): poses[n] for n, k in enumerate(keys)}
        self.edges = [PoseGraphEdge.from_dict(d) for d in state["edges"]]


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
