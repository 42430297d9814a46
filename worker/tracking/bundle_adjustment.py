"""Windowed bundle adjustment of keyframe poses and points: Levenberg-Marquardt with a Huber kernel, solved on the
reduced camera system (the points are eliminated by the Schur complement), all in vectorised numpy.

`bundle_adjustment_gtsam.bundle_adjust` solves the same problem with GTSAM projection factors: it is the test
oracle and a few times slower on the problem sizes of a local window.

Cameras are parameterised world-to-camera, X_c = R X + t, updated on the left (T <- exp(xi) T, xi = (v, w)).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .projection import invert_pose, project, projection_jacobians


@dataclass
class Observations:
    """Keypoint observations: keyframe slot [O], point row [O], pixel uv [O, 2] and pixel sigma [O]."""

    keyframe: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    sigma: np.ndarray


def reprojection_chi2(poses: np.ndarray, points: np.ndarray, obs: Observations, K: np.ndarray) -> np.ndarray:
    """Squared reprojection error of each observation in sigmas (inf behind the camera)."""
    out = np.full(len(obs.point), np.inf)
    for k in np.unique(obs.keyframe):
        sel = np.flatnonzero(obs.keyframe == k)
        uv, z = project(points[obs.point[sel]], poses[k], K)
        out[sel] = np.where(z > 0, ((uv - obs.uv[sel]) ** 2).sum(1) / obs.sigma[sel] ** 2, np.inf)
    return out


class _Problem:
    """The residuals, robust weights and normal-equation blocks of one adjustment."""

    def __init__(self, obs: Observations, K: np.ndarray, huber: float) -> None:
        self.obs, self.K, self.huber = obs, K, huber
        self.info = 1.0 / obs.sigma ** 2

    def evaluate(self, R: np.ndarray, t: np.ndarray, X: np.ndarray):
        """Camera-frame points, pixel residuals and the robust cost."""
        o = self.obs
        pc = np.einsum("nij,nj->ni", R[o.keyframe], X[o.point]) + t[o.keyframe]
        z = np.maximum(pc[:, 2], 1e-9)
        K = self.K
        proj = np.stack([K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]], axis=1)
        r = proj - o.uv
        e2 = (r ** 2).sum(1) * self.info
        k2 = self.huber ** 2
        rho = np.where(e2 <= k2, e2, 2 * self.huber * np.sqrt(e2) - k2)
        rho = np.where(pc[:, 2] > 1e-6, rho, 0.0)
        return pc, r, float(rho.sum())

    def weights(self, pc: np.ndarray, r: np.ndarray) -> np.ndarray:
        e = np.sqrt((r ** 2).sum(1) * self.info)
        w = np.where(e <= self.huber, 1.0, self.huber / np.maximum(e, 1e-12))
        return self.info * w * (pc[:, 2] > 1e-6)

    def jacobians(self, R: np.ndarray, pc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """d(pixel)/d(xi) [O, 2, 6] and d(pixel)/d(X) [O, 2, 3]."""
        J_proj, J_pose = projection_jacobians(pc, self.K)
        return J_pose, J_proj @ R[self.obs.keyframe]


def _pairs(point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) observation pairs that share a point (i, j indexing `point`, i == j included)."""
    order = np.argsort(point, kind="stable")
    sorted_points = point[order]
    start = np.searchsorted(sorted_points, sorted_points, side="left")
    end = np.searchsorted(sorted_points, sorted_points, side="right")
    counts = end - start
    i = np.repeat(order, counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    j = order[np.repeat(start, counts) + offsets]
    return i, j


def bundle_adjust(poses: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs: Observations, K: np.ndarray,
                  iterations: int = 10, huber: float = 2.45) -> tuple[np.ndarray, np.ndarray, bool]:
    """Adjusted (poses [F, 4, 4] camera-to-world, points [P, 3]) and whether the solve ran; unchanged on failure.

    `fixed` [F] marks the keyframes held still. Only points with two or more observations move; the others (and
    their observations) are left out."""
    counts = np.bincount(obs.point, minlength=len(points))
    use = counts[obs.point] >= 2
    if use.sum() < 6 or fixed.all():
        return poses, points, False
    used_points, point_index = np.unique(obs.point[use], return_inverse=True)
    free = np.flatnonzero(~fixed)
    slot = np.full(len(poses), -1)
    slot[free] = np.arange(len(free))
    sub = Observations(obs.keyframe[use], point_index, obs.uv[use], obs.sigma[use])
    problem = _Problem(sub, K, huber)
    w2c = np.stack([invert_pose(p) for p in poses])
    R, t, X = w2c[:, :3, :3].copy(), w2c[:, :3, 3].copy(), points[used_points].copy()
    pi, pj = _pairs(sub.point)
    fi, fj = slot[sub.keyframe[pi]], slot[sub.keyframe[pj]]
    keep_pairs = (fi >= 0) & (fj >= 0)
    pi, pj, fi, fj = pi[keep_pairs], pj[keep_pairs], fi[keep_pairs], fj[keep_pairs]
    pc, r, cost = problem.evaluate(R, t, X)
    lam = 1e-3
    n_free, n_pts = len(free), len(X)
    for _ in range(iterations):
        w = problem.weights(pc, r)
        J_pose, J_point = problem.jacobians(R, pc)
        Jw_pose = J_pose * w[:, None, None]
        Jw_point = J_point * w[:, None, None]
        U_obs = np.einsum("nik,nil->nkl", Jw_pose, J_pose)
        W_obs = np.einsum("nik,nil->nkl", Jw_pose, J_point)
        V = np.zeros((n_pts, 3, 3))
        np.add.at(V, sub.point, np.einsum("nik,nil->nkl", Jw_point, J_point))
        g_pose = np.einsum("nik,ni->nk", Jw_pose, r)
        g_point = np.zeros((n_pts, 3))
        np.add.at(g_point, sub.point, np.einsum("nik,ni->nk", Jw_point, r))
        improved = False
        while not improved and lam < 1e8:
            V_damped = V + lam * (V * np.eye(3)) + 1e-9 * np.eye(3)
            V_inv = np.linalg.inv(V_damped)
            Y = W_obs @ V_inv[sub.point]  # [O, 6, 3]
            S = np.zeros((n_free, n_free, 6, 6))
            b = np.zeros((n_free, 6))
            own = slot[sub.keyframe]
            mine = own >= 0
            np.add.at(S, (own[mine], own[mine]), U_obs[mine])
            np.add.at(b, own[mine], -g_pose[mine] + np.einsum("nij,nj->ni", Y[mine], g_point[sub.point[mine]]))
            np.add.at(S, (fi, fj), -Y[pi] @ W_obs[pj].transpose(0, 2, 1))
            S = S.transpose(0, 2, 1, 3).reshape(6 * n_free, 6 * n_free)
            S += lam * np.diag(np.diag(S)) + 1e-9 * np.eye(6 * n_free)
            try:
                dx = np.linalg.solve(S, b.ravel()).reshape(n_free, 6)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dx_obs = np.zeros((len(sub.point), 6))
            dx_obs[mine] = dx[own[mine]]
            rhs = -g_point.copy()
            np.add.at(rhs, sub.point, -np.einsum("nji,nj->ni", W_obs, dx_obs))
            dX = np.einsum("nij,nj->ni", V_inv, rhs)
            R_new, t_new = R.copy(), t.copy()
            for k, f in enumerate(free):
                dR = cv2.Rodrigues(dx[k, 3:])[0]
                R_new[f], t_new[f] = dR @ R[f], dR @ t[f] + dx[k, :3]
            X_new = X + dX
            pc_new, r_new, cost_new = problem.evaluate(R_new, t_new, X_new)
            if np.isfinite(cost_new) and cost_new < cost:
                R, t, X, pc, r = R_new, t_new, X_new, pc_new, r_new
                converged = cost - cost_new < 1e-6 * cost
                cost, lam, improved = cost_new, max(lam / 10, 1e-7), True
                if converged:
                    break
            else:
                lam *= 10
        if not improved or converged:
            break
    out_poses, out_points = poses.copy(), points.copy()
    for f in free:
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R[f], t[f]
        out_poses[f] = invert_pose(w2c)
    out_points[used_points] = X
    if not (np.all(np.isfinite(out_poses)) and np.all(np.isfinite(out_points))):
        return poses, points, False
    return out_poses, out_points, True
