"""Dense RGB-D frame alignment: the rigid motion that maps a reference RGB-D frame onto the current one.

Coarse-to-fine Gauss-Newton over an image pyramid on two kinds of residual, each with its own robust (Huber) scale
estimated from the residuals themselves:
- photometric: intensity of a reference pixel minus the current image sampled where its 3D point lands (minus the
  median difference, which absorbs a global brightness change such as auto-exposure);
- geometric: point-to-plane distance between the moved reference point and the current frame's surface at the
  pixel it projects to (projective association).
The update is a left perturbation exp(delta) T of T_cur_ref (p_cur = T p_ref). Pixel centres are at +0.5 (see
worker.geometry.camera); every threshold is relative to depth, so nothing assumes metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MIN_POINTS = 60  # per pyramid level; fewer leave six degrees of freedom poorly constrained


@dataclass
class PyramidLevel:
    """One resolution of an RGB-D frame: intensity, its gradients, camera-frame points and normals, K."""

    grey: np.ndarray  # float32 [h, w] in [0, 1]
    grad_x: np.ndarray
    grad_y: np.ndarray
    points: np.ndarray  # float32 [h, w, 3], z = 0 where depth is unknown
    normals: np.ndarray  # float32 [h, w, 3], 0 where undefined
    K: np.ndarray  # float64 [3, 3]


@dataclass
class AlignmentResult:
    """T_cur_ref (4x4 float64), the fraction of reference points that found the current surface within the
    geometric threshold (overlap), the robust residual scales and whether the solve stayed well posed."""

    T: np.ndarray
    overlap: float
    photometric_rms: float
    geometric_rms: float
    ok: bool
    points_used: int


def _downsample_depth(depth: np.ndarray, edge_ratio: float) -> np.ndarray:
    """2x2 blocks -> mean of valid depths, 0 where the block straddles a depth edge or has no valid depth."""
    h, w = depth.shape[0] // 2 * 2, depth.shape[1] // 2 * 2
    blocks = depth[:h, :w].reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3).reshape(h // 2, w // 2, 4)
    valid = blocks > 0
    count = valid.sum(-1)
    mean = np.where(count > 0, blocks.sum(-1) / np.maximum(count, 1), 0.0)
    hi = np.where(valid, blocks, 0.0).max(-1)
    lo = np.where(valid, blocks, np.inf).min(-1)
    keep = (count >= 2) & (hi - lo <= edge_ratio * mean)
    return np.where(keep, mean, 0.0).astype(np.float32)


def _points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    u = (np.arange(w, dtype=np.float32) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(h, dtype=np.float32) + 0.5 - K[1, 2]) / K[1, 1]
    return np.stack([u[None, :] * depth, v[:, None] * depth, depth], axis=-1).astype(np.float32)


def _normals(points: np.ndarray, edge_ratio: float) -> np.ndarray:
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


def build_pyramid(grey: np.ndarray, depth: np.ndarray, K: np.ndarray, levels: int,
                  edge_ratio: float = 0.05) -> list[PyramidLevel]:
    """Levels from full resolution (index 0) down by 2 each; `grey` float32 [0, 1], `depth` float32 (0 = none)."""
    out: list[PyramidLevel] = []
    K = np.asarray(K, np.float64)
    for level in range(levels):
        if level > 0:
            grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
            depth = _downsample_depth(depth, edge_ratio)
            K = K.copy()
            K[:2] *= 0.5
        gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        pts = _points(depth, K)
        out.append(PyramidLevel(grey, gx, gy, pts, _normals(pts, edge_ratio), K))
    return out


def _skew_jacobian(p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Rows d(a . (exp(delta) p))/d(omega, v) = [p x a, a] for direction vectors a [N, 3] at points p [N, 3]."""
    return np.concatenate([np.cross(p, a), a], axis=1)


def _huber_weights(r: np.ndarray, scale: float, k: float = 1.345) -> np.ndarray:
    a = np.abs(r) / max(scale, 1e-12)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _robust_scale(r: np.ndarray, floor: float) -> float:
    if r.size == 0:
        return floor
    return max(1.4826 * float(np.median(np.abs(r - np.median(r)))), floor)


def _se3_exp(delta: np.ndarray) -> np.ndarray:
    omega, v = delta[:3], delta[3:]
    theta = float(np.linalg.norm(omega))
    W = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    if theta < 1e-10:
        R, V = np.eye(3) + W, np.eye(3) + 0.5 * W
    else:
        a, b = np.sin(theta) / theta, (1 - np.cos(theta)) / theta**2
        c = (1 - a) / theta**2
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + c * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def _select(level: PyramidLevel, max_points: int, min_gradient: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of reference pixels for the photometric term (textured, with depth) and the geometric term
    (with a normal), each at most `max_points`, spread evenly over the image."""
    z = level.points[..., 2].ravel()
    grad = np.hypot(level.grad_x, level.grad_y).ravel()
    photo = np.flatnonzero((z > 0) & (grad > min_gradient))
    geo = np.flatnonzero(np.abs(level.normals[..., 2]).ravel() > 0)
    if photo.size > max_points:
        photo = photo[np.argsort(-grad[photo], kind="stable")[: 2 * max_points]]
        photo = np.sort(photo)[:: max(1, photo.size // max_points)]
    if geo.size > max_points:
        geo = geo[:: int(np.ceil(geo.size / max_points))]
    return photo, geo


def _sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples at continuous pixel coordinates (centres at +0.5)."""
    mx = (u - 0.5).astype(np.float32).reshape(-1, 1)
    my = (v - 0.5).astype(np.float32).reshape(-1, 1)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1)


def _project(p: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = np.maximum(p[:, 2], 1e-9)
    return K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]


@dataclass
class AlignmentSettings:
    """Iterations per level (coarse to fine), points per term, the weight of the photometric term relative to the
    geometric one (both whitened by their robust scales) and the association threshold (relative to depth)."""

    iterations: tuple[int, ...] = (10, 8, 6)
    max_points: int = 5000
    min_gradient: float = 0.02
    photometric_weight: float = 1.0
    geometric_weight: float = 1.0
    max_association: float = 0.08
    photometric_floor: float = 0.004
    geometric_floor: float = 0.0005


def align(reference: list[PyramidLevel], current: list[PyramidLevel], T_init: np.ndarray,
          settings: AlignmentSettings | None = None) -> AlignmentResult:
    """T_cur_ref refined from `T_init` by coarse-to-fine Gauss-Newton (see the module docstring)."""
    s = settings or AlignmentSettings()
    T = np.asarray(T_init, np.float64).copy()
    levels = min(len(reference), len(current), len(s.iterations))
    overlap, rms_i, rms_g, used, ok = 0.0, 0.0, 0.0, 0, True
    for level in reversed(range(levels)):
        ref, cur = reference[level], current[level]
        h, w = cur.grey.shape
        photo, geo = _select(ref, s.max_points, s.min_gradient)
        P_photo = ref.points.reshape(-1, 3)[photo].astype(np.float64)
        I_ref = ref.grey.ravel()[photo].astype(np.float64)
        P_geo = ref.points.reshape(-1, 3)[geo].astype(np.float64)
        cur_points = cur.points.reshape(-1, 3)
        cur_normals = cur.normals.reshape(-1, 3)
        for _ in range(s.iterations[level]):
            H = np.zeros((6, 6))
            g = np.zeros(6)
            count = 0
            # photometric term
            p = P_photo @ T[:3, :3].T + T[:3, 3]
            u, v = _project(p, cur.K)
            inside = (p[:, 2] > 0) & (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
            if int(inside.sum()) >= MIN_POINTS:
                pi, ui, vi = p[inside], u[inside], v[inside]
                r = _sample(cur.grey, ui, vi) - I_ref[inside]
                r -= np.median(r)
                gx, gy = _sample(cur.grad_x, ui, vi), _sample(cur.grad_y, ui, vi)
                z = pi[:, 2]
                # d(intensity)/d(point) = grad . d(pixel)/d(point)
                a = np.stack([gx * cur.K[0, 0] / z, gy * cur.K[1, 1] / z,
                              -(gx * cur.K[0, 0] * pi[:, 0] + gy * cur.K[1, 1] * pi[:, 1]) / z**2], axis=1)
                J = _skew_jacobian(pi, a)
                scale = _robust_scale(r, s.photometric_floor)
                wts = _huber_weights(r, scale) * (s.photometric_weight / scale**2)
                H += (J * wts[:, None]).T @ J
                g += (J * wts[:, None]).T @ r
                rms_i = scale
                count += r.size
            # geometric term
            p = P_geo @ T[:3, :3].T + T[:3, 3]
            u, v = _project(p, cur.K)
            inside = (p[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            idx = np.flatnonzero(inside)
            flat = (v[idx].astype(np.int64)) * w + u[idx].astype(np.int64)
            q, n = cur_points[flat].astype(np.float64), cur_normals[flat].astype(np.float64)
            pi = p[idx]
            close = (q[:, 2] > 0) & (np.abs(n).sum(1) > 0) & (
                np.linalg.norm(pi - q, axis=1) < s.max_association * pi[:, 2])
            overlap = float(close.sum()) / max(1, P_geo.shape[0])
            if int(close.sum()) >= MIN_POINTS:
                pi, q, n = pi[close], q[close], n[close]
                r = ((pi - q) * n).sum(1) / pi[:, 2]  # relative to depth: scale-free
                J = _skew_jacobian(pi, n) / pi[:, 2:3]
                scale = _robust_scale(r, s.geometric_floor)
                wts = _huber_weights(r, scale) * (s.geometric_weight / scale**2)
                H += (J * wts[:, None]).T @ J
                g += (J * wts[:, None]).T @ r
                rms_g = scale
                count += r.size
            if count < MIN_POINTS:
                ok = False
                break
            H += 1e-9 * np.trace(H) * np.eye(6)
            try:
                delta = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                ok = False
                break
            if not np.all(np.isfinite(delta)):
                ok = False
                break
            T = _se3_exp(delta) @ T
            used = count
            if np.linalg.norm(delta) < 1e-6:
                break
        if not ok:
            break
    return AlignmentResult(T, overlap, rms_i, rms_g, ok and bool(np.all(np.isfinite(T))), used)
