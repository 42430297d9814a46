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
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    candidates = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    best = candidates.argmax(dim=-1)
    s = torch.sqrt(candidates.gather(1, best[:, None]).squeeze(1).clamp_min(1e-12)) * 2  # 4 * |component|
    q = torch.empty(m.shape[0], 4, dtype=R.dtype, device=R.device)
    b0, b1, b2, b3 = (best == i for i in range(4))
    q[b0] = torch.stack([0.25 * s[b0], (m[b0, 2, 1] - m[b0, 1, 2]) / s[b0],
                         (m[b0, 0, 2] - m[b0, 2, 0]) / s[b0], (m[b0, 1, 0] - m[b0, 0, 1]) / s[b0]], -1)
    q[b1] = torch.stack([(m[b1, 2, 1] - m[b1, 1, 2]) / s[b1], 0.25 * s[b1],
                         (m[b1, 0, 1] + m[b1, 1, 0]) / s[b1], (m[b1, 0, 2] + m[b1, 2, 0]) / s[b1]], -1)
    q[b2] = torch.stack([(m[b2, 0, 2] - m[b2, 2, 0]) / s[b2], (m[b2, 0, 1] + m[b2, 1, 0]) / s[b2],
                         0.25 * s[b2], (m[b2, 1, 2] + m[b2, 2, 1]) / s[b2]], -1)
    q[b3] = torch.stack([(m[b3, 1, 0] - m[b3, 0, 1]) / s[b3], (m[b3, 0, 2] + m[b3, 2, 0]) / s[b3],
                         (m[b3, 1, 2] + m[b3, 2, 1]) / s[b3], 0.25 * s[b3]], -1)
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
