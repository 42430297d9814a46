"""An independent, slow, float64 per-pixel 2DGS renderer with gsplat 1.5.3's rules (test oracle only).

Written from the maths (cross product of the two pixel planes, AABB of the r = 1 conic, 16x16 tile rule, sequential
front-to-back loop) without using the rasterizer's own modules.
"""

from __future__ import annotations

import math

import numpy as np


def _rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def render_oracle(means, quats, scales, opacities, colors, viewmat, K, width, height, background=(0, 0, 0)):
    """(rgb [H,W,3], depth [H,W], alpha [H,W], normals_world [H,W,3]) as float64 numpy arrays."""
    means, quats, scales = (np.asarray(a, dtype=np.float64) for a in (means, quats, scales))
    opacities, colors = np.asarray(opacities, np.float64), np.asarray(colors, np.float64)
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    R_cw, t_cw = viewmat[:3, :3], viewmat[:3, 3]
    surfels = []
    for k in range(means.shape[0]):
        mu_c = R_cw @ means[k] + t_cw
        if mu_c[2] <= 0.01 or mu_c[2] >= 1e10:
            continue
        R_c = R_cw @ _rotmat(quats[k])
        T = K @ np.stack([scales[k, 0] * R_c[:, 0], scales[k, 1] * R_c[:, 1], mu_c], axis=1)
        t = np.array([1.0, 1.0, -1.0])
        d = np.sum(t * T[2] * T[2])
        if d == 0:
            continue
        f = t / d
        cx, cy = np.sum(f * T[0] * T[2]), np.sum(f * T[1] * T[2])
        hx = math.sqrt(max(1e-4, cx * cx - np.sum(f * T[0] * T[0])))
        hy = math.sqrt(max(1e-4, cy * cy - np.sum(f * T[1] * T[1])))
        rx, ry = math.ceil(3.33 * hx), math.ceil(3.33 * hy)
        if cx + rx <= 0 or cx - rx >= width or cy + ry <= 0 or cy - ry >= height:
            continue
        n = R_c[:, 2] * (1.0 if np.dot(-R_c[:, 2], mu_c) > 0 else -1.0)
        tiles_x, tiles_y = (width + 15) // 16, (height + 15) // 16
        tx = (min(max(math.floor((cx - rx) / 16), 0), tiles_x), min(max(math.ceil((cx + rx) / 16), 0), tiles_x))
        ty = (min(max(math.floor((cy - ry) / 16), 0), tiles_y), min(max(math.ceil((cy + ry) / 16), 0), tiles_y))
        surfels.append(dict(k=k, T=T, c=(cx, cy), z=mu_c[2], n=n, tx=tx, ty=ty))
    surfels.sort(key=lambda s: s["z"])  # Python's sort is stable: ties keep surfel order
    rgb = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    alpha_img = np.zeros((height, width))
    normals = np.zeros((height, width, 3))
    if not surfels:
        rgb[:] = background
        return rgb, depth, alpha_img, normals
    Ts = np.stack([s["T"] for s in surfels])
    centres = np.array([s["c"] for s in surfels])
    tx = np.array([s["tx"] for s in surfels])
    ty = np.array([s["ty"] for s in surfels])
    ks = np.array([s["k"] for s in surfels])
    for i in range(height):
        for j in range(width):
            x, y = j + 0.5, i + 0.5
            # candidates: surfels whose tile rectangle holds this pixel's tile, in depth order
            cand = np.nonzero((tx[:, 0] <= j // 16) & (j // 16 < tx[:, 1]) & (ty[:, 0] <= i // 16)
                              & (i // 16 < ty[:, 1]))[0]
            T = Ts[cand]
            p = np.cross(x * T[:, 2] - T[:, 0], y * T[:, 2] - T[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
            rho = np.minimum(u * u + v * v, 2.0 * ((x - centres[cand, 0]) ** 2 + (y - centres[cand, 1]) ** 2))
            alphas = np.minimum(0.999, opacities[ks[cand]] * np.exp(-0.5 * rho))
            T_pix, C, D, N = 1.0, np.zeros(3), 0.0, np.zeros(3)
            for c, a, p2 in zip(cand, alphas, p[:, 2]):
                if p2 == 0 or not a >= 1.0 / 255.0:
                    continue
                next_T = T_pix * (1 - a)
                if next_T <= 1e-4:
                    break
                w = a * T_pix
                C += w * colors[ks[c]]
                D += w * surfels[c]["z"]
                N += w * surfels[c]["n"]
                T_pix = next_T
            acc = 1 - T_pix
            rgb[i, j] = C + T_pix * np.asarray(background, np.float64)
            alpha_img[i, j] = acc
            depth[i, j] = D / max(acc, 1e-10)
            normals[i, j] = R_cw.T @ N
    return rgb, depth, alpha_img, normals
