"""Numpy reference of the compiled kernels (csrc/mvs_cpu.cpp): the same maths, slower; the test oracle and the
fallback when no C++ compiler is available. Signatures match `mvs_cpu` (its `out` / `scratch` buffers are ignored).
"""

from __future__ import annotations

import numpy as np

from .decide import DecisionTerms
from .sweep import window_counts, window_sums

UNSEEN = -1.0
SGM_DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1))


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    H, W = img.shape
    u, v = np.clip(u, 0.0, W - 1), np.clip(v, 0.0, H - 1)
    x0 = np.minimum(u.astype(np.int64), W - 2)
    y0 = np.minimum(v.astype(np.int64), H - 2)
    fx, fy = (u - x0).astype(np.float32), (v - y0).astype(np.float32)
    a, b = img[y0, x0], img[y0, x0 + 1]
    c, d = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    top, bottom = a + fx * (b - a), c + fx * (d - c)
    return top + fy * (bottom - top)


def cost_volume(ref: np.ndarray, ref_sum: np.ndarray, ref_ssd: np.ndarray, views: np.ndarray, A: np.ndarray,
                b: np.ndarray, inv_depths: np.ndarray, radius: int, min_var: float, threads: int = 1,
                out: np.ndarray | None = None) -> np.ndarray:
    """1 - ZNCC of each view warped onto each plane, float32 [N, D, H, W]; UNSEEN where the view misses the pixel."""
    N, H, W = views.shape
    ys, xs = np.mgrid[0:H, 0:W]
    p = np.stack([xs + 0.5, ys + 0.5, np.ones((H, W))], axis=-1)  # [H, W, 3]
    n = window_counts(H, W, radius)
    volume = np.empty((N, len(inv_depths), H, W), dtype=np.float32)
    for i in range(N):
        base = p @ A[i].T
        for d, w in enumerate(inv_depths):
            h = base + w * b[i]
            front = h[..., 2] > 1e-9
            z = np.where(front, h[..., 2], 1.0)
            u = np.where(front, h[..., 0] / z - 0.5, 0.0)
            v = np.where(front, h[..., 1] / z - 0.5, 0.0)
            seen = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
            warped = _bilinear(views[i], u, v)
            s1, s2 = window_sums(warped, radius), window_sums(warped * warped, radius)
            s3 = window_sums(ref * warped, radius)
            var_w, var_r = s2 - s1 * s1 / n, ref_ssd.astype(np.float64)
            textured = (var_w > n * min_var) & (var_r > n * min_var)
            cov = s3 - ref_sum.astype(np.float64) * s1 / n
            zncc = np.where(textured, cov / np.sqrt(np.where(textured, var_r * var_w, 1.0)), 0.0)
            volume[i, d] = np.where(seen, 1.0 - np.clip(zncc, -1.0, 1.0), UNSEEN)
    return volume


def fuse_views(cost: np.ndarray, keep: int, threads: int = 1,
               out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(fused [H, W, D]: mean of the `keep` lowest seen view costs, 1 where none sees; view_min [N, H, W]: each
    view's lowest seen cost over the hypotheses, UNSEEN where it never sees the pixel)."""
    seen = cost >= 0
    ranked = np.sort(np.where(seen, cost, np.inf), axis=0)
    used = np.minimum(seen.sum(axis=0), keep)  # [D, H, W]
    top = ranked[:keep]
    total = np.where(np.arange(len(top))[:, None, None, None] < used, top, 0.0).sum(axis=0)
    fused = np.where(used > 0, total / np.maximum(used, 1), 1.0).astype(np.float32)
    view_min = np.where(seen, cost, np.inf).min(axis=1)
    view_min = np.where(np.isfinite(view_min), view_min, UNSEEN).astype(np.float32)
    return np.ascontiguousarray(fused.transpose(1, 2, 0)), view_min


def _sgm_step(c: np.ndarray, prev: np.ndarray, p1: float, p2: float) -> np.ndarray:
    m = prev.min(axis=-1, keepdims=True)
    v = np.minimum(prev, m + np.float32(p2))
    v[..., 1:] = np.minimum(v[..., 1:], prev[..., :-1] + np.float32(p1))
    v[..., :-1] = np.minimum(v[..., :-1], prev[..., 1:] + np.float32(p1))
    return c + v - m


def sgm(cost: np.ndarray, p1: float, p2: float, paths: int, threads: int = 1, out: np.ndarray | None = None,
        scratch: np.ndarray | None = None) -> np.ndarray:
    """Sum over `paths` directions of the semi-global path costs of cost [H, W, D], float32 [H, W, D]."""
    H, W, D = cost.shape
    total = np.zeros_like(cost)
    for dx, dy in SGM_DIRECTIONS[:paths]:
        L = np.empty_like(cost)
        if dy == 0:
            cols = range(W) if dx > 0 else range(W - 1, -1, -1)
            for k, x in enumerate(cols):
                L[:, x] = cost[:, x] if k == 0 else _sgm_step(cost[:, x], L[:, x - dx], p1, p2)
        else:
            rows = range(H) if dy > 0 else range(H - 1, -1, -1)
            for k, y in enumerate(rows):
                if k == 0:
                    L[y] = cost[y]
                    continue
                row = cost[y].copy()
                lo, hi = max(0, dx), min(W, W + dx)  # pixels whose predecessor x - dx is inside the row
                row[lo:hi] = _sgm_step(cost[y, lo:hi], L[y - dy, lo - dx:hi - dx], p1, p2)
                L[y] = row
        total += L
    return total


def _take(volume: np.ndarray, index: np.ndarray) -> np.ndarray:
    """volume [H, W, D] at index [H, W]."""
    return np.take_along_axis(volume, index[..., None], axis=-1)[..., 0]


def decide_terms(total: np.ndarray, fused: np.ndarray, cost: np.ndarray, view_min: np.ndarray, margin: float,
                 max_cost: float, threads: int = 1) -> DecisionTerms:
    """Per-pixel decision terms from total [H, W, D], fused [H, W, D], cost [N, D, H, W], view_min [N, H, W]."""
    D = total.shape[-1]
    best = np.argmin(total, axis=-1)
    interior = (best > 0) & (best < D - 1)
    a, b, c = (_take(fused, np.clip(best + k, 0, D - 1)).astype(np.float64) for k in (-1, 0, 1))
    curvature = a - 2.0 * b + c  # the fit uses the matching cost: SGM's penalties pull towards whole hypotheses
    delta = np.where(interior & (curvature > 0), 0.5 * (a - c) / np.where(curvature > 0, curvature, 1.0), 0.0)
    far = np.abs(np.arange(D) - best[..., None]) > 1
    runner_up = np.where(far, total, np.inf).min(axis=-1).astype(np.float64)
    lowest = _take(total, best).astype(np.float64)
    ratio = np.where(runner_up > 0, lowest / np.where(runner_up > 0, runner_up, 1.0), 1.0)
    support = np.zeros(best.shape, dtype=np.int16)
    for n in range(cost.shape[0]):
        near = np.full(best.shape, np.inf, dtype=np.float32)
        for k in (-1, 0, 1):
            view = np.take_along_axis(cost[n], np.clip(best + k, 0, D - 1)[None], axis=0)[0]
            near = np.minimum(near, np.where(view >= 0, view, np.inf))
        support += (np.isfinite(near) & (near <= view_min[n] + np.float32(margin)) & (near <= max_cost)).astype(
            np.int16)
    rival = np.where(np.abs(np.arange(D) - best[..., None]) > 2, fused, np.float32(2.0)).min(axis=-1)
    return DecisionTerms(index=best + np.clip(delta, -0.5, 0.5), interior=interior,
                         uniqueness=np.clip(1.0 - ratio, 0.0, 1.0).astype(np.float32),
                         margin=np.maximum(rival - _take(fused, best), 0.0).astype(np.float32),
                         photometric=np.clip(1.0 - _take(fused, best), 0.0, 1.0).astype(np.float32),
                         support=support)
