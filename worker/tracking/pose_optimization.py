"""Motion-only pose refinement: robust (Huber) Gauss-Newton of one camera against fixed 3D points, with rounds
that set outliers aside (their chi2 is re-judged after each round, so a point wrongly dropped can come back).

The camera is parameterised world-to-camera, X_c = R X + t, and updated on the left: T <- exp(xi) T with
xi = (v, w), so dX_c/dxi = [I | -[X_c]_x].
"""

from __future__ import annotations

import cv2
import numpy as np

from .projection import invert_pose, projection_jacobians, rigid


def _residuals(R: np.ndarray, t: np.ndarray, points: np.ndarray, uv: np.ndarray, K: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    pc = points @ R.T + t
    z = np.maximum(pc[:, 2], 1e-9)
    proj = np.stack([K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]], axis=1)
    return proj - uv, pc


def _gauss_newton(R, t, points, uv, info, K, huber, iterations):
    for _ in range(iterations):
        r, pc = _residuals(R, t, points, uv, K)
        e = np.sqrt((r ** 2).sum(1) * info)
        w = info * np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-12)) * (pc[:, 2] > 1e-6)
        J = projection_jacobians(pc, K)[1].reshape(-1, 6)  # rows (u, v) of each match
        Jw = J * np.repeat(w, 2)[:, None]
        H, g = Jw.T @ J, Jw.T @ r.ravel()
        try:
            xi = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(xi)):
            break
        dR = cv2.Rodrigues(xi[3:])[0]
        R, t = dR @ R, dR @ t + xi[:3]
        if np.linalg.norm(xi) < 1e-8:
            break
    return R, t


def optimize_pose(pose_c2w: np.ndarray, points: np.ndarray, uv: np.ndarray, sigma: np.ndarray, K: np.ndarray,
                  chi2: float = 5.991, rounds: int = 4, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Refined camera-to-world pose and the inlier mask [N] of 2D-3D matches (points [N, 3], pixels uv [N, 2],
    pixel noise sigma [N]). The Huber width is sqrt(chi2) sigmas; a match is an inlier when its squared error in
    sigmas is below chi2 and its point lies in front of the camera."""
    w2c = invert_pose(rigid(pose_c2w))
    R, t = w2c[:3, :3].copy(), w2c[:3, 3].copy()
    info = 1.0 / sigma.astype(np.float64) ** 2
    inlier = np.ones(len(points), bool)
    huber = float(np.sqrt(chi2))
    for _ in range(rounds):
        if inlier.sum() < 3:
            break
        R, t = _gauss_newton(R, t, points[inlier], uv[inlier], info[inlier], K, huber, iterations)
        r, pc = _residuals(R, t, points, uv, K)
        inlier = ((r ** 2).sum(1) * info < chi2) & (pc[:, 2] > 0)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    return invert_pose(out), inlier


def pnp_pose(points: np.ndarray, uv: np.ndarray, K: np.ndarray, sigma: np.ndarray, chi2_px: float,
             min_inliers: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Camera-to-world pose of matches points [n, 3] <-> pixels uv [n, 2] found by EPnP + RANSAC (4 px) and
    refined by `optimize_pose`, with its inlier mask; None when either step keeps fewer than `min_inliers`."""
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points, uv, K, None, iterationsCount=200, reprojectionError=4.0,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < min_inliers:
        return None
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    pose, inlier = optimize_pose(invert_pose(w2c), points, uv, sigma, K, chi2_px)
    if inlier.sum() < min_inliers or not np.all(np.isfinite(pose)):
        return None
    return pose, inlier
