"""Similarity alignment: Umeyama's between point sets, and one between camera poses (rotations averaged, then
scale and translation by least squares on the centres)."""

from __future__ import annotations

import numpy as np
import torch

from .transforms import make_sim3


def umeyama(
    source: torch.Tensor, target: torch.Tensor, with_scale: bool = True, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Find (s, R, t) minimising sum_i w_i |target_i - (s R source_i + t)|^2 (Umeyama 1991).

    source, target: [N, 3]. Returns scalar s, R [3, 3] and t [3] in the inputs' dtype.
    """
    if source.shape != target.shape or source.shape[-1] != 3 or source.shape[0] < 3:
        raise ValueError(f"umeyama needs two [N>=3, 3] point sets, got {tuple(source.shape)}, {tuple(target.shape)}")
    x = source.double()
    y = target.double()
    w = torch.ones(x.shape[0], dtype=torch.float64, device=x.device) if weights is None else weights.double()
    w = w / w.sum()
    mu_x = (w[:, None] * x).sum(0)
    mu_y = (w[:, None] * y).sum(0)
    xc, yc = x - mu_x, y - mu_y
    var_x = (w * (xc * xc).sum(-1)).sum()
    cov = (w[:, None, None] * yc[:, :, None] * xc[:, None, :]).sum(0)
    U, D, Vt = torch.linalg.svd(cov)
    S = torch.eye(3, dtype=torch.float64, device=x.device)
    if torch.linalg.det(U) * torch.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = (D * S.diagonal()).sum() / var_x if with_scale else torch.ones((), dtype=torch.float64, device=x.device)
    t = mu_y - s * R @ mu_x
    dtype = source.dtype
    return s.to(dtype), R.to(dtype), t.to(dtype)


def umeyama_sim3(source: torch.Tensor, target: torch.Tensor, with_scale: bool = True) -> torch.Tensor:
    """Umeyama as one 4x4 similarity."""
    s, R, t = umeyama(source, target, with_scale)
    return make_sim3(R, t, s)


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest `M` [3, 3] (Frobenius norm)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt


def fit_similarity(own: list[np.ndarray], in_map: list[np.ndarray]) -> np.ndarray | None:
    """The similarity S with S @ own_i ~ in_map_i: rotation from the poses' rotations, scale and translation by
    least squares on the camera centres. None when the centres do not spread (no scale to measure)."""
    rotations = [m[:3, :3] @ (o[:3, :3] / np.cbrt(np.linalg.det(o[:3, :3]))).T for o, m in zip(own, in_map)]
    R = nearest_rotation(np.sum(rotations, axis=0))
    a = np.stack([R @ o[:3, 3] for o in own])
    b = np.stack([m[:3, 3] for m in in_map])
    a0, b0 = a - a.mean(0), b - b.mean(0)
    spread = float(np.sum(a0 * a0))
    if spread <= 1e-12:
        return None
    scale = float(np.sum(a0 * b0) / spread)
    if scale <= 0:
        return None
    out = np.eye(4)
    out[:3, :3] = scale * R
    out[:3, 3] = b.mean(0) - scale * a.mean(0)
    return out
