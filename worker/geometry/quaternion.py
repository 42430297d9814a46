"""Unit quaternions in (w, x, y, z) order, batched over leading dimensions."""

from __future__ import annotations

import torch


def quat_normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Scale quaternions to unit length."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] from (not necessarily unit) wxyz quaternions [..., 4]."""
    w, x, y, z = quat_normalize(q).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """wxyz unit quaternions [..., 4] (w >= 0) from rotation matrices [..., 3, 3].

    Uses the largest of the four candidate denominators for every matrix, so it is stable near 180 degrees.
    """
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    candidates = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    best = candidates.argmax(dim=-1)
    s = torch.sqrt(candidates.clamp_min(1e-12)) * 2  # 4 * |component| for each candidate denominator
    # every candidate's quaternion (without masked indexing, which costs more than the arithmetic), then the best
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    numerators = torch.stack([
        torch.stack([0.25 * s[:, 0] ** 2, wx, wy, wz], -1),
        torch.stack([wx, 0.25 * s[:, 1] ** 2, xy, xz], -1),
        torch.stack([wy, xy, 0.25 * s[:, 2] ** 2, yz], -1),
        torch.stack([wz, xz, yz, 0.25 * s[:, 3] ** 2], -1),
    ], 1)  # [N, candidate, wxyz], each to be divided by its s
    pick = best[:, None, None].expand(-1, 1, 4)
    q = numerators.gather(1, pick).squeeze(1) / s.gather(1, best[:, None])
    q = quat_normalize(q)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(R.shape[:-2] + (4,))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b (rotation b first, then a), wxyz."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse for unit quaternions)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_align_sign(q: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Flip each quaternion to the hemisphere of `reference` (q and -q are the same rotation)."""
    dot = (q * reference).sum(-1, keepdim=True)
    return torch.where(dot < 0, -q, q)
