"""The classical loop constraint: ORB matches between keyframes i and j, keyframe i's 3D points, PnP + RANSAC.

Keyframe i's camera-frame points (the tracker's prediction P_i, or points from given depth through `points_of`)
at its ORB keypoints and the matched keypoints in frame j give cv2.solvePnPRansac's X_j = R X_i + t (submap-a
units). The scale s (submap-b units -> a units) is the median depth ratio of the inliers between that solution and
j's incremental point map P_j^b, and the edge is H = [R|t]^-1 S(s) = T_i^-1 T_j, verified like the hidden-state
constraint (see worker.loop.relocalize).

Where ORB finds too few matches or PnP inliers (a revisit from a wide viewpoint change), XFeat matches of the two
keyframes (`worker.loop.xfeat_matcher`) go through the same PnP and verification, with more inliers needed
(`xfeat_min_inliers`), for the first `xfeat_per_keyframe` such candidates of a keyframe (source "pnp_xfeat").
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
from .xfeat_matcher import XFeatKeyframeMatcher


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
                 reprojection_px: float = 3.0, match_ratio: float = 0.85, xfeat: XFeatKeyframeMatcher | None = None,
                 xfeat_min_inliers: int = 50, xfeat_per_keyframe: int = 1) -> None:
        self.tracker = tracker
        self.orb = orb or OrbDescriptor()
        self.points_of = points_of or (lambda k: tracker.keyframe_points(k)[0])
        self.thresholds = thresholds or VerificationThresholds(min_point_agreement=0.0, min_support=0.3)
        self.min_inliers = min_inliers
        self.reprojection_px = reprojection_px
        self.match_ratio = match_ratio  # looser than for detection: RANSAC removes the wrong matches
        self.features: dict[int, OrbFeatures] = {}
        self.xfeat = xfeat  # None: ORB only
        self.xfeat_min_inliers, self.xfeat_per_keyframe = xfeat_min_inliers, xfeat_per_keyframe
        self._xfeat_tries: tuple[int, int] = (-1, 0)  # (query keyframe, XFeat verifications it had)
        self.xfeat_accepted = 0  # loops only XFeat verified

    def add_keyframe(self, index: int, image: torch.Tensor, features: OrbFeatures | None = None) -> OrbFeatures:
        """Keep keyframe `index`'s ORB features (computed here unless given, e.g. by the ORB loop detector) and,
        with XFeat verification, its image."""
        self.features[int(index)] = features if features is not None else self.orb.describe(image)
        if self.xfeat is not None:
            self.xfeat.add_keyframe(index, image)
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
        constraint = self._from_matches(i, j, fi.keypoints[ia], fj.keypoints[ib], points_i, points_j_b, K,
                                        self.min_inliers, self.source)
        if constraint.accepted or not constraint.extra.get("too_few") or not self._xfeat_try(i, j):
            return constraint
        uv_i, uv_j = self.xfeat.match(i, j)
        learned = self._from_matches(i, j, uv_i, uv_j, points_i, points_j_b, K, self.xfeat_min_inliers,
                                     "pnp_xfeat")
        if not learned.accepted:
            learned.reason = f"ORB: {constraint.reason}; XFeat: {learned.reason}"
            return learned
        self.xfeat_accepted += 1
        learned.extra["orb"] = constraint.reason
        return learned

    def _xfeat_try(self, i: int, j: int) -> bool:
        """Whether XFeat verifies this candidate: both keyframes' images are kept and query j has had fewer than
        `xfeat_per_keyframe` XFeat verifications (counted here)."""
        if self.xfeat is None or i not in self.xfeat or j not in self.xfeat:
            return False
        query, tries = self._xfeat_tries
        tries = tries if query == j else 0
        if tries >= self.xfeat_per_keyframe:
            return False
        self._xfeat_tries = (j, tries + 1)
        return True

    def _from_matches(self, i: int, j: int, uv_i: np.ndarray, uv_j: np.ndarray, points_i: torch.Tensor,
                      points_j_b: torch.Tensor, K: torch.Tensor, min_inliers: int, source: str) -> LoopConstraint:
        """The constraint from matched pixels of keyframes i and j ([n, 2] each): i's points at uv_i, PnP + RANSAC
        to uv_j, the scale from j's points, verified (a rejection for lack of matches or inliers says `too_few`)."""
        if len(uv_i) < min_inliers:
            kind = "ORB" if source == self.source else "XFeat"
            return self._rejected(i, j, f"{len(uv_i)} {kind} matches < {min_inliers}", too_few=True)
        X = _sample(points_i, uv_i)
        ok = torch.isfinite(X).all(-1) & (X[:, 2] > 0)
        X, uv = X[ok].numpy(), uv_j[ok.numpy()].astype(np.float64)
        if len(X) < min_inliers:
            return self._rejected(i, j, f"{len(X)} matches with valid depth < {min_inliers}", too_few=True)
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            X, uv, K.numpy(), None, iterationsCount=200, reprojectionError=self.reprojection_px, confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP)
        if not found or inliers is None or len(inliers) < min_inliers:
            return self._rejected(i, j, f"PnP found {0 if inliers is None else len(inliers)} inliers", too_few=True)
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[inl], K.numpy(), None, rvec, tvec)
        R = torch.from_numpy(cv2.Rodrigues(rvec)[0])
        t = torch.from_numpy(tvec.ravel())
        cam_j_from_i = make_sim3(R, t)
        z_a = (torch.from_numpy(X[inl]) @ R.T + t)[:, 2]
        z_b = _sample(points_j_b, uv[inl].astype(np.float32))[:, 2]
        good = (z_a > 0) & (z_b > 0)
        if int(good.sum()) < min_inliers:
            return self._rejected(i, j, "too few inliers with positive depth in both frames")
        s = float((z_a[good] / z_b[good]).median())
        relative = sim3_inverse(cam_j_from_i) @ scale_matrix(s)
        th = self.thresholds
        constraint = LoopConstraint(
            i, j, relative.numpy(), s, source,
            support=reprojection_support(relative, points_i, points_j_b, K, th.depth_tolerance),
            point_agreement=float(len(inl)) / len(X), confidence=float(len(inl)),
            extra={"matches": len(uv_i), "inliers": len(inl)},
        )
        return decide(constraint, th)
