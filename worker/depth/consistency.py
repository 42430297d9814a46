"""Geometric (left-right) consistency between two depth maps of the same camera: does b see a's points where a says?"""

from __future__ import annotations

import numpy as np


def reproject(depth: np.ndarray, pose: np.ndarray, other_pose: np.ndarray, K: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (column, row; int, nearest) and depths where the points of `depth` (camera-to-world `pose`) land in
    the camera at `other_pose`; flattened [H * W] arrays (depth <= 0 where behind that camera or invalid)."""
    H, W = depth.shape
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    z = depth.astype(np.float64)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], axis=-1).reshape(-1, 3)
    rel = np.linalg.inv(other_pose) @ pose
    other = cam @ rel[:3, :3].T + rel[:3, 3]
    zo = np.where(z.reshape(-1) > 0, other[:, 2], 0.0)
    safe = np.where(zo > 0, zo, 1.0)
    col = np.floor(K[0, 0] * other[:, 0] / safe + K[0, 2]).astype(np.int64)
    row = np.floor(K[1, 1] * other[:, 1] / safe + K[1, 2]).astype(np.int64)
    return col, row, zo


def cross_check(depth_a: np.ndarray, pose_a: np.ndarray, depth_b: np.ndarray, pose_b: np.ndarray, K: np.ndarray,
                rel_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """(agree, conflict) bool [H, W] over a's pixels with depth, where b has a depth at the pixel a's point lands on:
    agree when b's depth there is within `rel_tol` of the point's depth in b; conflict when b's is farther by more
    than that (b sees through the place where a puts a surface: one of the two is wrong). A point behind b's surface
    (occluded in b) is in neither, nor is a pixel b cannot check. The tolerance is relative: any scale works."""
    H, W = depth_a.shape
    col, row, z = reproject(depth_a, pose_a, pose_b, K)
    inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    seen = np.zeros(H * W)
    seen[inside] = depth_b[row[inside], col[inside]]
    checked = inside & (seen > 0)
    agree = checked & (np.abs(seen - z) <= rel_tol * z)
    conflict = checked & (seen > (1.0 + rel_tol) * z)
    return agree.reshape(H, W), conflict.reshape(H, W)
