"""The classical loop constraint: ORB matches between keyframes i and j, keyframe i's 3D points, PnP + RANSAC.

Keyframe i's camera-frame points (the tracker's prediction P_i, or points from given depth through `points_of`)
at its ORB keypoints and the matched keypoints in frame j give cv2.solvePnPRansac's X_j = R X_i + t (submap-a
units). The scale s (submap-b units -> a units) is the median depth ratio of the inliers between that solution and
j's incremental point map P_j^b, and the edge is H = [R|t]^-1 S(s) = T_i^-1 T_j, verified like the hidden-state
constraint (see worker.loop.relocalize).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import torch

from worker.geometry import Intrinsics, make_sim3, sim3_inverse

from .descriptors import OrbDescriptor, OrbFeatures
from .relocalize import (
    LoopConstraint,
    VerificationThresholds,
    decide,
    intrinsics_for,
    reprojection_support,
    scale_matrix,
)


def _sample(points: torch.Tensor, keypoints: np.ndarray) -> torch.Tensor:
    """Point-map values [N,3] at keypoint pixel positions (nearest pixel)."""
    H, W = points.shape[:2]
    col = np.clip(keypoints[:, 0].astype(np.int64), 0, W - 1)
    row = np.clip(keypoints[:, 1].astype(np.int64), 0, H - 1)
    return points[torch.from_numpy(row), torch.from_numpy(col)].double()


class PnPRelocalizer:
    """Loop constraints by PnP + RANSAC on ORB matches; same `relocalize` interface as HiddenStateRelocalizer."""

    source = "pnp"

    def __init__(self, tracker, orb: OrbDescriptor | None = None,
                 points_of: Callable[[int], torch.Tensor] | None = None,
                 thresholds: VerificationThresholds | None = None, min_inliers: int = 30,
                 reprojection_px: float = 3.0, match_ratio: float = 0.85) -> None:
        self.tracker = tracker
        self.orb = orb or OrbDescriptor()
        self.points_of = points_of or (lambda k: tracker.keyframe_points(k)[0])
        self.thresholds = thresholds or VerificationThresholds(min_point_agreement=0.0, min_support=0.3)
        self.min_inliers = min_inliers
        self.reprojection_px = reprojection_px
        self.match_ratio = match_ratio  # looser than for detection: RANSAC removes the wrong matches
        self.features: dict[int, OrbFeatures] = {}

    def add_keyframe(self, index: int, image: torch.Tensor, features: OrbFeatures | None = None) -> OrbFeatures:
        """Keep keyframe `index`'s ORB features (computed here unless given, e.g. by the ORB loop detector)."""
        self.features[int(index)] = features if features is not None else self.orb.describe(image)
        return self.features[int(index)]

    def _rejected(self, i: int, j: int, reason: str, **extra) -> LoopConstraint:
        return LoopConstraint(i, j, np.eye(4), 1.0, self.source, support=0.0, point_agreement=0.0, accepted=False,
                              reason=reason, extra=extra)

    def relocalize(self, i: int, j: int, image_j: torch.Tensor, intrinsics: Intrinsics | None = None
                   ) -> LoopConstraint:
        if i not in self.features:
            raise ValueError(f"no ORB features stored for keyframe {i}")
        points_i = self.points_of(i).float()
        points_j_b, conf_j_b = self.tracker.keyframe_points(j)
        try:
            K = intrinsics_for(points_j_b, intrinsics, conf_j_b).matrix(torch.float64)
        except ValueError as err:
            return self._rejected(i, j, str(err))
        fi = self.features[i]
        fj = self.features.get(j) or self.orb.describe(image_j)
        ia, ib = self.orb.match(fi, fj, self.match_ratio)
        if len(ia) < self.min_inliers:
            return self._rejected(i, j, f"{len(ia)} ORB matches < {self.min_inliers}")
        X = _sample(points_i, fi.keypoints[ia])
        ok = torch.isfinite(X).all(-1) & (X[:, 2] > 0)
        X, uv = X[ok].numpy(), fj.keypoints[ib][ok.numpy()].astype(np.float64)
        if len(X) < self.min_inliers:
            return self._rejected(i, j, f"{len(X)} matches with valid depth < {self.min_inliers}")
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            X, uv, K.numpy(), None, iterationsCount=200, reprojectionError=self.reprojection_px, confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP)
        if not found or inliers is None or len(inliers) < self.min_inliers:
            return self._rejected(i, j, f"PnP found {0 if inliers is None else len(inliers)} inliers")
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[inl], K.numpy(), None, rvec, tvec)
        R = torch.from_numpy(cv2.Rodrigues(rvec)[0])
        t = torch.from_numpy(tvec.ravel())
        cam_j_from_i = make_sim3(R, t)
        z_a = (torch.from_numpy(X[inl]) @ R.T + t)[:, 2]
        z_b = _sample(points_j_b, uv[inl].astype(np.float32))[:, 2]
        good = (z_a > 0) & (z_b > 0)
        if int(good.sum()) < self.min_inliers:
            return self._rejected(i, j, "too few inliers with positive depth in both frames")
        s = float((z_a[good] / z_b[good]).median())
        relative = sim3_inverse(cam_j_from_i) @ scale_matrix(s)
        th = self.thresholds
        constraint = LoopConstraint(
            i, j, relative.numpy(), s, self.source,
            support=reprojection_support(relative, points_i, points_j_b, K, th.depth_tolerance),
            point_agreement=float(len(inl)) / len(X), confidence=float(len(inl)),
            extra={"matches": len(ia), "inliers": len(inl)},
        )
        return decide(constraint, th)
