"""Pinhole projection of world points into a camera posed camera-to-world (numpy, float64)."""

from __future__ import annotations

import numpy as np

from worker.geometry import Intrinsics


def camera_matrix(intrinsics: Intrinsics) -> np.ndarray:
    """K [3, 3] float64."""
    return np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]])


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    out = np.eye(4)
    R = pose[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ pose[:3, 3]
    return out


def rigid(pose: np.ndarray) -> np.ndarray:
    """The nearest rigid transform to a 4x4 pose: its rotation block projected onto SO(3) (products of many
    poses drift off it)."""
    U, _, Vt = np.linalg.svd(pose[:3, :3])
    out = np.eye(4)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[:3, 3] = pose[:3, 3]
    return out


def to_camera(points: np.ndarray, pose_c2w: np.ndarray) -> np.ndarray:
    """World points [N, 3] in the frame of a camera at `pose_c2w`."""
    R, t = pose_c2w[:3, :3], pose_c2w[:3, 3]
    return (points - t) @ R


def project(points: np.ndarray, pose_c2w: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [N, 2] and z-depths [N] of world points [N, 3] (pixels are meaningless where z <= 0)."""
    pc = to_camera(points, pose_c2w)
    z = pc[:, 2]
    zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
    uv = np.stack([K[0, 0] * pc[:, 0] / zs + K[0, 2], K[1, 1] * pc[:, 1] / zs + K[1, 2]], axis=1)
    return uv, z


def in_image(uv: np.ndarray, z: np.ndarray, width: int, height: int, margin: float = 0.0) -> np.ndarray:
    """Mask of projections in front of the camera and inside the image (less `margin` pixels)."""
    return ((z > 1e-6) & (uv[:, 0] >= margin) & (uv[:, 0] < width - margin) & (uv[:, 1] >= margin)
            & (uv[:, 1] < height - margin))


def bearings(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit viewing rays [N, 3] in the camera frame through pixels uv [N, 2]."""
    rays = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def projection_jacobians(pc: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d(pixel)/d(camera point) [N, 2, 3] and d(pixel)/d(xi) [N, 2, 6] for camera points pc [N, 3], where the
    world-to-camera transform is updated on the left, T <- exp(xi) T with xi = (v, w): dX_c/dxi = [I | -[X_c]_x]."""
    x, y, z = pc[:, 0], pc[:, 1], np.maximum(pc[:, 2], 1e-9)
    fx, fy = K[0, 0], K[1, 1]
    inv_z = 1.0 / z
    xz, yz = x * inv_z, y * inv_z
    J = np.zeros((len(pc), 2, 6))
    # translation part: J_proj itself
    J[:, 0, 0], J[:, 0, 2] = fx * inv_z, -fx * xz * inv_z
    J[:, 1, 1], J[:, 1, 2] = fy * inv_z, -fy * yz * inv_z
    # rotation part: J_proj @ -[X_c]_x written out (the same entries as the product, without it)
    J[:, 0, 3], J[:, 0, 4], J[:, 0, 5] = -fx * xz * yz, fx * (1.0 + xz * xz), -fx * yz
    J[:, 1, 3], J[:, 1, 4], J[:, 1, 5] = -fy * (1.0 + yz * yz), fy * xz * yz, fy * xz
    return J[:, :, :3], J


def sparse_depth_image(points: np.ndarray, uv: np.ndarray, pose_c2w: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """z-depth [H, W] float32 of world points [N, 3] at their pixels uv [N, 2] in the camera posed `pose_c2w` (the
    keypoints that see them), 0 elsewhere and behind the camera."""
    depth = np.zeros((camera.height, camera.width), np.float32)
    z = to_camera(points, pose_c2w)[:, 2]
    col = np.clip(uv[:, 0].astype(np.int64), 0, camera.width - 1)
    row = np.clip(uv[:, 1].astype(np.int64), 0, camera.height - 1)
    keep = z > 0
    depth[row[keep], col[keep]] = z[keep]
    return depth
