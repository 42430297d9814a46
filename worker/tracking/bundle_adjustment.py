"""Windowed bundle adjustment of keyframe poses and points: Levenberg-Marquardt with a Huber kernel, solved on the
reduced camera system (the points are eliminated by the Schur complement), in vectorised numpy (sums by index through
np.bincount) but for the sum over observation pairs, compiled (`schur_native`, numpy fallback beside it).

`bundle_adjustment_gtsam.bundle_adjust` solves the same problem with GTSAM projection factors: it is the test
oracle and a few times slower on the problem sizes of a local window.

Cameras are parameterised world-to-camera, X_c = R X + t, updated on the left (T <- exp(xi) T, xi = (v, w)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from . import schur_native
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


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """out[i] = the sum of values[k] over k with index[k] == i, for i < n ([n, *values.shape[1:]]): np.add.at's
    sums in np.add.at's order, through np.bincount (many times faster)."""
    flat = values.reshape(len(values), -1)
    m = flat.shape[1]
    bins = (index[:, None] * m + np.arange(m)).ravel()
    return np.bincount(bins, weights=flat.ravel(), minlength=n * m).reshape(n, *values.shape[1:])


class _PairTerm:
    """The observation-pair part of the reduced camera system, -sum Y_i W_j^T over pairs (i, j) of observations
    of one point by free keyframes, as a dense [6 F, 6 F] matrix: compiled (`schur_native`) or in numpy (pairs
    sorted by keyframe pair once, each block sum one np.add.reduceat)."""

    def __init__(self, pi: np.ndarray, pj: np.ndarray, fi: np.ndarray, fj: np.ndarray, n_free: int,
                 native: bool) -> None:
        key = fi * n_free + fj
        order = np.argsort(key, kind="stable")
        self.pi, self.pj, self.fi, self.fj, self.n_free, self.native = pi[order], pj[order], fi[order], fj[order], \
            n_free, native
        sorted_key = key[order]
        self.starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]]) if len(key) else key[:0]
        self.rows, self.cols = np.divmod(sorted_key[self.starts], n_free)

    def __call__(self, Y: np.ndarray, W: np.ndarray) -> np.ndarray:
        n = self.n_free
        S = np.zeros((6 * n, 6 * n))
        if len(self.pi) == 0:
            return S
        if self.native:
            schur_native.subtract_pairs(S, self.pi, self.pj, self.fi, self.fj, Y, W)
            return S
        blocks = np.zeros((n, n, 6, 6))
        blocks[self.rows, self.cols] = -np.add.reduceat(Y[self.pi] @ W[self.pj].transpose(0, 2, 1), self.starts,
                                                        axis=0)
        return blocks.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)


def bundle_adjust(poses: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs: Observations, K: np.ndarray,
                  iterations: int = 10, huber: float = 2.45, backend: Literal["auto", "native", "reference"] = "auto"
                  ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Adjusted (poses [F, 4, 4] camera-to-world, points [P, 3]) and whether the solve ran; unchanged on failure.

    `fixed` [F] marks the keyframes held still. Only points with two or more observations move; the others (and
    their observations) are left out. The observation-pair sum runs compiled unless `backend="reference"` or the
    kernel cannot be built ("native" then raises)."""
    native = backend != "reference" and schur_native.available()
    if backend == "native" and not native:
        raise RuntimeError(f"compiled Schur kernel unavailable: {schur_native.load_error()}")
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
    n_free, n_pts = len(free), len(X)
    own = slot[sub.keyframe]  # the observing keyframe's free slot, -1 when held still
    mine = np.flatnonzero(own >= 0)
    seen_by = [np.flatnonzero(own == k) for k in range(n_free)]
    pair_term = _PairTerm(pi, pj, fi, fj, n_free, native)
    pc, r, cost = problem.evaluate(R, t, X)
    lam = 1e-3
    for _ in range(iterations):
        w = problem.weights(pc, r)
        J_pose, J_point = problem.jacobians(R, pc)
        Jw_pose = (J_pose * w[:, None, None]).transpose(0, 2, 1)  # [O, 6, 2]
        Jw_point = (J_point * w[:, None, None]).transpose(0, 2, 1)  # [O, 3, 2]
        U = np.stack([Jw_pose[seen].transpose(1, 0, 2).reshape(6, -1) @ J_pose[seen].reshape(-1, 6)
                      for seen in seen_by])  # J^T w J of each free keyframe's observations
        W_obs = Jw_pose @ J_point  # [O, 6, 3]
        V = _sum_by(sub.point, Jw_point @ J_point, n_pts)
        g_pose = (Jw_pose @ r[:, :, None])[:, :, 0]
        g_point = _sum_by(sub.point, (Jw_point @ r[:, :, None])[:, :, 0], n_pts)
        improved = False
        while not improved and lam < 1e8:
            V_damped = V + lam * (V * np.eye(3)) + 1e-9 * np.eye(3)
            V_inv = np.linalg.inv(V_damped)
            Y = W_obs @ V_inv[sub.point]  # [O, 6, 3]
            # reduced camera system S dx = b: S = U - sum over observation pairs of a point of Y_i W_j^T
            S = pair_term(Y, W_obs)
            for k in range(n_free):
                S[6 * k:6 * k + 6, 6 * k:6 * k + 6] += U[k]
            b = _sum_by(own[mine], -g_pose[mine] + (Y[mine] @ g_point[sub.point[mine], :, None])[:, :, 0], n_free)
            S += lam * np.diag(np.diag(S)) + 1e-9 * np.eye(6 * n_free)
            try:
                dx = np.linalg.solve(S, b.ravel()).reshape(n_free, 6)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dx_obs = np.zeros((len(sub.point), 6))
            dx_obs[mine] = dx[own[mine]]
            rhs = -g_point - _sum_by(sub.point, (W_obs.transpose(0, 2, 1) @ dx_obs[:, :, None])[:, :, 0], n_pts)
            dX = (V_inv @ rhs[:, :, None])[:, :, 0]
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
