"""Numpy reference of the dense-alignment kernels (csrc/dense_align.cpp): the same maths, slower; the test oracle
and the fallback when no C++ compiler is available. Signatures match `worker.tracking.dense_native`.

Per pyramid level: camera-frame points and normals of a depth map, and the 2x2 depth downsampling to the next
level. Per Gauss-Newton iteration, the normal equations (J^T W J, J^T W r) of the two residual terms of
`worker.tracking.dense_alignment`, each whitened by its own robust (MAD) scale with Huber weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

HUBER_K = 1.345


@dataclass
class TermSystem:
    """One residual term's normal equations: H = J^T W J [6, 6], g = J^T W r [6], the residuals used (0 when too
    few: H and g are then zero), their robust scale and, for the geometric term, the pairs found (overlap)."""

    H: np.ndarray
    g: np.ndarray
    used: int
    scale: float
    found: int = 0


def downsample_depth(depth: np.ndarray, edge_ratio: float) -> np.ndarray:
    """2x2 blocks -> mean of valid depths, 0 where the block straddles a depth edge or has under 2 valid depths."""
    h, w = depth.shape[0] // 2 * 2, depth.shape[1] // 2 * 2
    blocks = depth[:h, :w].reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3).reshape(h // 2, w // 2, 4)
    valid = blocks > 0
    count = valid.sum(-1)
    mean = np.where(count > 0, blocks.sum(-1) / np.maximum(count, 1), 0.0)
    hi = np.where(valid, blocks, 0.0).max(-1)
    lo = np.where(valid, blocks, np.inf).min(-1)
    keep = (count >= 2) & (hi - lo <= edge_ratio * mean)
    return np.where(keep, mean, 0.0).astype(np.float32)


def points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points float32 [h, w, 3] (z = depth, 0 where unknown)."""
    h, w = depth.shape
    u = (np.arange(w, dtype=np.float32) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(h, dtype=np.float32) + 0.5 - K[1, 2]) / K[1, 1]
    return np.stack([u[None, :] * depth, v[:, None] * depth, depth], axis=-1).astype(np.float32)


def normals(points: np.ndarray, edge_ratio: float) -> np.ndarray:
    """Normals from central differences of the point grid (0 across depth edges and at missing depth)."""
    n = np.zeros_like(points)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    cross = np.empty_like(dx)  # dx x dy, written out: np.cross is several times slower on image-sized arrays
    cross[..., 0] = dx[..., 1] * dy[..., 2] - dx[..., 2] * dy[..., 1]
    cross[..., 1] = dx[..., 2] * dy[..., 0] - dx[..., 0] * dy[..., 2]
    cross[..., 2] = dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0]
    norm = np.sqrt(np.einsum("...k,...k->...", cross, cross))
    z = points[1:-1, 1:-1, 2]
    limit = edge_ratio * z
    good = (z > 0) & (norm > 0)
    for neighbour in (points[1:-1, 2:, 2], points[1:-1, :-2, 2], points[2:, 1:-1, 2], points[:-2, 1:-1, 2]):
        good &= (neighbour > 0) & (np.abs(neighbour - z) <= limit)
    # Unit length, oriented towards the camera (the point's own ray): n . p < 0.
    facing = np.einsum("...k,...k->...", cross, points[1:-1, 1:-1])
    scale = np.where(good, np.where(facing > 0, -1.0, 1.0) / np.maximum(norm, 1e-12), 0.0).astype(points.dtype)
    n[1:-1, 1:-1] = cross * scale[..., None]
    return n


def _skew_jacobian(p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Rows d(a . (exp(delta) p))/d(omega, v) = [p x a, a] for direction vectors a [N, 3] at points p [N, 3]."""
    return np.concatenate([np.cross(p, a), a], axis=1)


def _huber_weights(r: np.ndarray, scale: float, k: float = HUBER_K) -> np.ndarray:
    a = np.abs(r) / max(scale, 1e-12)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _robust_scale(r: np.ndarray, floor: float) -> float:
    if r.size == 0:
        return floor
    return max(1.4826 * float(np.median(np.abs(r - np.median(r)))), floor)


def _sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples at continuous pixel coordinates (centres at +0.5)."""
    mx = (u - 0.5).astype(np.float32).reshape(-1, 1)
    my = (v - 0.5).astype(np.float32).reshape(-1, 1)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1)


def _project(p: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = np.maximum(p[:, 2], 1e-9)
    return K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]


def _system(J: np.ndarray, r: np.ndarray, scale: float, weight: float, found: int = 0) -> TermSystem:
    wts = _huber_weights(r, scale) * (weight / scale**2)
    Jw = J * wts[:, None]
    return TermSystem(Jw.T @ J, Jw.T @ r, int(r.size), scale, found)


def _empty(found: int = 0) -> TermSystem:
    return TermSystem(np.zeros((6, 6)), np.zeros(6), 0, 0.0, found)


def photometric_system(P: np.ndarray, intensity: np.ndarray, T: np.ndarray, K: np.ndarray, grey: np.ndarray,
                       grad_x: np.ndarray, grad_y: np.ndarray, floor: float, weight: float, min_points: int
                       ) -> TermSystem:
    """Reference points P [n, 3] (float64) of intensity [n] moved by T (T_cur_ref) and projected into the current
    image: r = sampled intensity - reference intensity, minus its median (a global brightness change)."""
    h, w = grey.shape
    p = P @ T[:3, :3].T + T[:3, 3]
    u, v = _project(p, K)
    inside = (p[:, 2] > 0) & (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    if int(inside.sum()) < min_points:
        return _empty()
    pi, ui, vi = p[inside], u[inside], v[inside]
    r = _sample(grey, ui, vi) - intensity[inside]
    r -= np.median(r)
    gx, gy = _sample(grad_x, ui, vi), _sample(grad_y, ui, vi)
    z = pi[:, 2]
    # d(intensity)/d(point) = grad . d(pixel)/d(point)
    a = np.stack([gx * K[0, 0] / z, gy * K[1, 1] / z, -(gx * K[0, 0] * pi[:, 0] + gy * K[1, 1] * pi[:, 1]) / z**2],
                 axis=1)
    return _system(_skew_jacobian(pi, a), r, _robust_scale(r, floor), weight)


def geometric_system(P: np.ndarray, T: np.ndarray, K: np.ndarray, cur_points: np.ndarray, cur_normals: np.ndarray,
                     max_association: float, floor: float, weight: float, min_points: int) -> TermSystem:
    """Reference points P [n, 3] (float64) moved by T and associated with the current frame's point and normal at
    the pixel they project to (within max_association x depth): r = (p - q) . n / z (relative to depth)."""
    h, w = cur_points.shape[:2]
    p = P @ T[:3, :3].T + T[:3, 3]
    u, v = _project(p, K)
    inside = (p[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.flatnonzero(inside)
    flat = (v[idx].astype(np.int64)) * w + u[idx].astype(np.int64)
    q = cur_points.reshape(-1, 3)[flat].astype(np.float64)
    n = cur_normals.reshape(-1, 3)[flat].astype(np.float64)
    pi = p[idx]
    close = (q[:, 2] > 0) & (np.abs(n).sum(1) > 0) & (np.linalg.norm(pi - q, axis=1) < max_association * pi[:, 2])
    found = int(close.sum())
    if found < min_points:
        return _empty(found)
    pi, q, n = pi[close], q[close], n[close]
    r = ((pi - q) * n).sum(1) / pi[:, 2]  # relative to depth: scale-free
    J = _skew_jacobian(pi, n) / pi[:, 2:3]
    return _system(J, r, _robust_scale(r, floor), weight, found)
