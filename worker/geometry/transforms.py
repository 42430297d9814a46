"""SE(3) and Sim(3) as 4x4 matrices [s*R | t; 0 1], batched over leading dimensions.

A similarity T maps points p -> s * R @ p + t. SE(3) is the special case s = 1, so every function here accepts
both. Poses are camera-to-world unless a name says otherwise.
"""

from __future__ import annotations

import numpy as np
import torch

from .quaternion import quat_to_rotmat, rotmat_to_quat


def make_sim3(R: torch.Tensor, t: torch.Tensor, s: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Build [..., 4, 4] from rotation [..., 3, 3], translation [..., 3] and scale [...] (or a float)."""
    s = torch.as_tensor(s, dtype=R.dtype, device=R.device)
    T = torch.zeros(R.shape[:-2] + (4, 4), dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R * s[..., None, None]
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def sim3_from_quat(q: torch.Tensor, t: torch.Tensor, s: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Build [..., 4, 4] from a wxyz quaternion, translation and scale."""
    return make_sim3(quat_to_rotmat(q), t, s)


def sim3_scale(T: torch.Tensor) -> torch.Tensor:
    """The scale s of [..., 4, 4] similarities (cube root of det(sR))."""
    det = torch.linalg.det(T[..., :3, :3])
    return det.sign() * det.abs().pow(1.0 / 3.0)


def se3_part(T: np.ndarray) -> np.ndarray:
    """The rigid part of a 4x4 Sim(3) matrix (numpy): the scale divided out of the rotation, translation kept."""
    out = np.array(T, np.float64)
    out[:3, :3] /= np.cbrt(np.linalg.det(out[:3, :3]))
    return out


def nearest_sim3(T: np.ndarray) -> np.ndarray:
    """The similarity nearest a 4x4 matrix whose 3x3 block has drifted from s*R (numpy): R from the SVD's
    U V^T, s the mean singular value, translation kept. Poses built by chains of products and closed-form
    inverses must go through it: the closed-form inverse of a sheared matrix is not its inverse, so a shear of
    1e-13 grows tenfold every few keyframes (seen on TUM fr1/xyz: 1e-4 after 350 frames, then a pose-graph blow-up)."""
    out = np.array(T, np.float64)
    u, singular, vt = np.linalg.svd(out[:3, :3])
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:  # a reflection is no similarity: keep the proper rotation nearest
        u[:, -1] *= -1
        rotation = u @ vt
    out[:3, :3] = rotation * singular.mean()
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def sim3_decompose(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split [..., 4, 4] into (s [...], R [..., 3, 3], t [..., 3])."""
    s = sim3_scale(T)
    return s, T[..., :3, :3] / s[..., None, None], T[..., :3, 3]


def sim3_to_quat(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split [..., 4, 4] into (s, wxyz quaternion, t)."""
    s, R, t = sim3_decompose(T)
    return s, rotmat_to_quat(R), t


def sim3_inverse(T: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse: (sR, t)^-1 = (R^T / s, -R^T t / s)."""
    s, R, t = sim3_decompose(T)
    Rt = R.transpose(-1, -2)
    return make_sim3(Rt, -(Rt @ t[..., None])[..., 0] / s[..., None], 1.0 / s)


def sim3_compose(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """A * B (apply B first)."""
    return A @ B


def sim3_apply(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Transform points [..., N, 3] by T [..., 4, 4] (broadcast over leading dims)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def sim3_blend(A: torch.Tensor, B: torch.Tensor, alpha: float) -> torch.Tensor:
    """The similarity `alpha` of the way from A to B: rotation along the geodesic, translation and log-scale linear
    (alpha 0 gives A, 1 gives B)."""
    s_a, R_a, t_a = sim3_decompose(A)
    s_b, R_b, t_b = sim3_decompose(B)
    R = R_a @ so3_exp(alpha * so3_log(R_a.transpose(-1, -2) @ R_b))
    s = s_a * (s_b / s_a) ** alpha
    return make_sim3(R, t_a + alpha * (t_b - t_a), s)


def relative_transform(T_a: torch.Tensor, T_b: torch.Tensor) -> torch.Tensor:
    """T_a^-1 * T_b: the pose of b expressed in the frame of a."""
    return sim3_inverse(T_a) @ T_b


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle [..., 3] -> rotation [..., 3, 3] (differentiable, safe at zero)."""
    theta2 = (omega * omega).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    wx, wy, wz = omega.unbind(-1)
    zero = torch.zeros_like(wx)
    K = torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], -1).reshape(omega.shape + (3,))
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Inverse of so3_exp, via the quaternion (stable for all angles)."""
    q = rotmat_to_quat(R)
    w = q[..., :1].clamp(-1.0, 1.0)
    v = q[..., 1:]
    n = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(n, w)
    factor = torch.where(n < 1e-12, 2.0 / w.clamp_min(1e-12), angle / n.clamp_min(1e-12))
    return v * factor


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Small-motion update: xi = (rho [3], omega [3]) -> 4x4 with R = exp(omega), t = rho (first-order)."""
    R = so3_exp(xi[..., 3:])
    return make_sim3(R, xi[..., :3])
