"""Which two-view model explains a set of matches: a homography (a plane, or a rotation without parallax) or the
epipolar geometry of a general scene. Each model is scored by its symmetric transfer error as ORB-SLAM does (Mur-Artal
et al. 2015, section IV): per match and direction, a squared error under the model's chi2 bound (one pixel sigma)
adds `GAMMA - error`, a larger one nothing; R_H = S_H / (S_H + S_F) above `HOMOGRAPHY_RATIO` picks the homography.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHI2_HOMOGRAPHY = 5.991  # 2 degrees of freedom (a point against a point), 95 %
CHI2_FUNDAMENTAL = 3.841  # 1 degree of freedom (a point against a line), 95 %
GAMMA = CHI2_HOMOGRAPHY  # both scores count in the homography's units, so that they compare
HOMOGRAPHY_RATIO = 0.45


@dataclass
class ModelScores:
    """Scores of the homography and of the fundamental matrix, their inlier masks [N] and the ratio R_H."""

    homography: float
    fundamental: float
    inliers_h: np.ndarray
    inliers_f: np.ndarray

    @property
    def ratio(self) -> float:
        total = self.homography + self.fundamental
        return self.homography / total if total > 0 else 0.0

    @property
    def prefers_homography(self) -> bool:
        return self.ratio > HOMOGRAPHY_RATIO


def _homogeneous(p: np.ndarray) -> np.ndarray:
    return np.concatenate([p, np.ones((len(p), 1))], axis=1)


def _score(chi2: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
    inside = chi2 < bound
    return np.where(inside, GAMMA - chi2, 0.0), inside


def homography_score(H: np.ndarray, pa: np.ndarray, pb: np.ndarray, sigma: float = 1.0) -> tuple[float, np.ndarray]:
    """Score and inlier mask of H (pb ~ H pa) over matches pa, pb [N, 2]: transfer error both ways."""
    total, inlier = np.zeros(len(pa)), np.ones(len(pa), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for M, src, dst in ((H, pa, pb), (np.linalg.inv(H), pb, pa)):
            q = _homogeneous(src) @ M.T
            err2 = ((q[:, :2] / q[:, 2:] - dst) ** 2).sum(1) / sigma ** 2
            err2 = np.where(np.isfinite(err2), err2, np.inf)
            s, ok = _score(err2, CHI2_HOMOGRAPHY)
            total += s
            inlier &= ok
    return float(total.sum()), inlier


def fundamental_score(F: np.ndarray, pa: np.ndarray, pb: np.ndarray, sigma: float = 1.0
                      ) -> tuple[float, np.ndarray]:
    """Score and inlier mask of F (pb^T F pa = 0) over matches pa, pb [N, 2]: distance to the epipolar line in
    each image."""
    a, b = _homogeneous(pa), _homogeneous(pb)
    total, inlier = np.zeros(len(pa)), np.ones(len(pa), bool)
    for line, point in ((a @ F.T, b), (b @ F, a)):  # line in b of each point of a, line in a of each point of b
        num = (line * point).sum(1) ** 2
        err2 = num / np.maximum((line[:, :2] ** 2).sum(1), 1e-30) / sigma ** 2
        s, ok = _score(err2, CHI2_FUNDAMENTAL)
        total += s
        inlier &= ok
    return float(total.sum()), inlier


def score_models(H: np.ndarray | None, F: np.ndarray | None, pa: np.ndarray, pb: np.ndarray) -> ModelScores:
    """Both scores over the same matches (a model that could not be fitted scores 0)."""
    none = np.zeros(len(pa), bool)
    s_h, in_h = homography_score(H, pa, pb) if H is not None else (0.0, none)
    s_f, in_f = fundamental_score(F, pa, pb) if F is not None else (0.0, none)
    return ModelScores(s_h, s_f, in_h, in_f)


def rotation_of_homography(H: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The rotation R_ba (X_b = R_ba X_a) nearest to K^-1 H K: exact for a pure rotation (H = K R K^-1 up to
    scale), the rotation part of a small motion otherwise."""
    M = np.linalg.inv(K) @ H @ K
    if np.linalg.det(M) < 0:  # H is known up to a sign
        M = -M
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R
