"""Camera-to-world poses as the wire carries them: a similarity [sR | t; 0 0 0 1], 16 floats row-major."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def similarity_scale(pose: Sequence[float] | np.ndarray) -> float:
    """s = cbrt(|det(3x3 block)|) of a 4x4 pose (or its 16 row-major floats), sent beside every pose."""
    block = np.asarray(pose, dtype=np.float64).reshape(4, 4)[:3, :3]
    return float(np.cbrt(abs(np.linalg.det(block))))


def rotation_to_quaternion(rotations: np.ndarray) -> np.ndarray:
    """wxyz unit quaternions [N, 4] (w >= 0) of rotation matrices [N, 3, 3].

    Each matrix uses the largest of the four candidate denominators, so it stays stable near 180 degrees.
    """
    m = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    candidates = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = candidates.argmax(-1)
    s = np.sqrt(np.maximum(candidates, 1e-12)) * 2  # 4 |component| for each candidate denominator
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    numerators = np.stack([
        np.stack([0.25 * s[:, 0] ** 2, wx, wy, wz], -1),
        np.stack([wx, 0.25 * s[:, 1] ** 2, xy, xz], -1),
        np.stack([wy, xy, 0.25 * s[:, 2] ** 2, yz], -1),
        np.stack([wz, xz, yz, 0.25 * s[:, 3] ** 2], -1),
    ], 1)  # [N, candidate, wxyz], each divided by its s below
    rows = np.arange(len(m))
    q = numerators[rows, best] / s[rows, best][:, None]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)


def split_similarity(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(s [N], wxyz quaternion [N, 4], t [N, 3]) of similarities [N, 4, 4] (or [N, 16] row-major)."""
    mats = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    det = np.linalg.det(mats[:, :3, :3])
    scale = np.sign(det) * np.cbrt(np.abs(det))
    return scale, rotation_to_quaternion(mats[:, :3, :3] / scale[:, None, None]), mats[:, :3, 3]
