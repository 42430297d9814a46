"""Loop constraints from a verified candidate (paper 4.2, eq. 12-13), and their geometric verification.

Convention: a loop between old keyframe i (submap a) and current keyframe j (submap b) yields the Sim(3) edge
H = T_i^-1 T_j of the pose graph, where the node poses carry their submap's units. With the relocalized pose
T_j^a = f(I_j, M_a) and keyframe i's pose T_i^a in submap a:  H = (T_i^a)^-1 T_j^a S(s),  S(s) = diag(s,s,s,1),
where s maps submap-b camera units into submap-a units: s = argmin sum_k |P_j^a - s P_j^b|^2 (eq. 12 solved
for the inverse of the paper's s*). The rotation block of H is then s R (eq. 13).

Verification rejects a candidate unless (1) the relocalized point map agrees with the incremental one after
scaling (fraction of pixels within `point_tolerance`), (2) keyframe i's points, moved into frame j with H, land in
j's image with a depth matching P_j^b on at least `min_support` of them, and (3) the relocalization confidence is
at least `min_confidence`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import torch

from worker.frontend.tracker import relative_scale
from worker.geometry import Intrinsics, project_points, relative_transform, sim3_apply, sim3_inverse

from .pose_graph import PoseGraphEdge


@dataclass(frozen=True)
class VerificationThresholds:
    point_tolerance: float = 0.05
    min_point_agreement: float = 0.5
    depth_tolerance: float = 0.1
    min_support: float = 0.2
    min_confidence: float = 0.0


@dataclass
class LoopConstraint:
    """A loop edge candidate i (old) <- j (current): relative = T_i^-1 T_j (Sim(3)) and its verification."""

    i: int
    j: int
    relative: np.ndarray
    scale: float
    source: str
    support: float
    point_agreement: float = 1.0
    confidence: float = 0.0
    accepted: bool = False
    reason: str = ""
    extra: dict = field(default_factory=dict)

    def to_edge(self, weight: float = 1.0) -> PoseGraphEdge:
        return PoseGraphEdge(self.i, self.j, self.relative, "loop", weight)


class Relocalizer(Protocol):
    source: str

    def relocalize(self, i: int, j: int, image_j: torch.Tensor, intrinsics: Intrinsics | None = None
                   ) -> LoopConstraint:
        """Constraint between old keyframe i and current keyframe j (whose image is given)."""


def scale_matrix(s: float) -> torch.Tensor:
    return torch.diag(torch.tensor([s, s, s, 1.0], dtype=torch.float64))


def intrinsics_for(points: torch.Tensor, intrinsics: Intrinsics | None, conf: torch.Tensor | None = None
                   ) -> Intrinsics:
    """The given intrinsics, or ones estimated from a camera-frame point map [H,W,3] (uncalibrated input)."""
    H, W = points.shape[:2]
    if intrinsics is not None:
        if (intrinsics.width, intrinsics.height) != (W, H):
            raise ValueError(f"intrinsics are for {intrinsics.width}x{intrinsics.height}, point map is {W}x{H}")
        return intrinsics
    from worker.frontend.focal import estimate_focal, intrinsics_from_focal

    return intrinsics_from_focal(float(estimate_focal(points.float(), conf)), W, H)


def reprojection_support(relative: torch.Tensor, points_i: torch.Tensor, points_j: torch.Tensor, K: torch.Tensor,
                         depth_tolerance: float = 0.1, max_points: int = 5000) -> float:
    """Fraction of keyframe i's points that, moved into camera j (X_j = H^-1 X_i), land in j's image in front of
    the camera with a depth within `depth_tolerance` (relative) of j's own point map there."""
    P = points_i.reshape(-1, 3).double()
    P = P[torch.isfinite(P).all(-1) & (P[:, 2] > 0)]
    if len(P) == 0:
        return 0.0
    P = P[:: max(1, len(P) // max_points)]
    X = sim3_apply(sim3_inverse(relative.double()), P)
    uv, z = project_points(X, K.double())
    H, W = points_j.shape[:2]
    inside = (z > 1e-9) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    if not inside.any():
        return 0.0
    col, row = uv[inside, 0].long(), uv[inside, 1].long()
    zj = points_j[row, col, 2].double()
    good = (zj > 0) & ((z[inside] - zj).abs() <= depth_tolerance * zj)
    return float(good.sum()) / len(P)


def point_agreement(target: torch.Tensor, source: torch.Tensor, s: float, tolerance: float) -> float:
    """Fraction of pixels with |target - s source| <= tolerance |target|."""
    a, b = target.reshape(-1, 3).double(), source.reshape(-1, 3).double()
    valid = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1) & (a[:, 2] > 0)
    if not valid.any():
        return 0.0
    r = (a[valid] - s * b[valid]).norm(dim=-1) / a[valid].norm(dim=-1)
    return float((r <= tolerance).double().mean())


def decide(c: LoopConstraint, th: VerificationThresholds) -> LoopConstraint:
    """Set `accepted` and `reason` from the thresholds."""
    if c.point_agreement < th.min_point_agreement:
        c.accepted, c.reason = False, f"point agreement {c.point_agreement:.2f} < {th.min_point_agreement}"
    elif c.support < th.min_support:
        c.accepted, c.reason = False, f"reprojection support {c.support:.2f} < {th.min_support}"
    elif c.confidence < th.min_confidence:
        c.accepted, c.reason = False, f"confidence {c.confidence:.2f} < {th.min_confidence}"
    else:
        c.accepted, c.reason = True, "verified"
    return c


class HiddenStateRelocalizer:
    """f(I_j, M_a) with the cached state read-only -> T_j^a, P_j^a -> Sim(3) loop constraint (eq. 12-13).

    model: anything with `step(image, state, update=False)`; bag: HiddenStateBag; tracker: SubmapTracker (gives
    T_i^a, keyframe i's points and P_j^b).
    """

    source = "hidden_state"

    def __init__(self, model, bag, tracker, thresholds: VerificationThresholds | None = None) -> None:
        self.model = model
        self.bag = bag
        self.tracker = tracker
        self.thresholds = thresholds or VerificationThresholds()

    @torch.no_grad()
    def relocalize(self, i: int, j: int, image_j: torch.Tensor, intrinsics: Intrinsics | None = None
                   ) -> LoopConstraint:
        _, state_a = self.bag.state_for_keyframe(i)
        if i not in self.tracker.keyframes:
            raise ValueError(f"frame {i} is not a keyframe")
        pose_i_a = self.tracker.keyframes[i].pose_submap.double()
        points_j_b, conf_j_b = self.tracker.keyframe_points(j)
        points_i, _ = self.tracker.keyframe_points(i)
        out = self.model.step(image_j, state_a, update=False)
        pose_j_a = out.pose_c2w[0].double()
        points_j_a, conf_j_a = out.points_cam[0], out.conf[0]
        weights = (conf_j_a.float() * conf_j_b.float()).sqrt()
        try:
            s = relative_scale(points_j_a, points_j_b, weights)
            K = intrinsics_for(points_j_b, intrinsics, conf_j_b).matrix(torch.float64)
        except ValueError as err:  # degenerate point maps: no constraint, say why
            return LoopConstraint(i, j, np.eye(4), 1.0, self.source, support=0.0, point_agreement=0.0,
                                  confidence=float(conf_j_a.float().mean()), accepted=False, reason=str(err))
        relative = relative_transform(pose_i_a, pose_j_a) @ scale_matrix(s)
        th = self.thresholds
        constraint = LoopConstraint(
            i, j, relative.numpy(), s, self.source,
            support=reprojection_support(relative, points_i, points_j_b, K, th.depth_tolerance),
            point_agreement=point_agreement(points_j_a, points_j_b, s, th.point_tolerance),
            confidence=float(conf_j_a.float().mean()),
        )
        return decide(constraint, th)
