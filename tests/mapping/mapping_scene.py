"""A synthetic textured plane seen by pinhole cameras: ground-truth images, depth and per-pixel surfels."""

from __future__ import annotations

import math

import torch

from worker.geometry import make_sim3, pixel_grid, rotmat_to_quat, so3_exp
from worker.mapping import Surfels
from worker.mapping.voxelize import voxelize

WIDTH, HEIGHT = 64, 48
FOCAL = 60.0
PLANE_Z = 2.0


def intrinsics() -> torch.Tensor:
    return torch.tensor([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]])


def texture(xy: torch.Tensor) -> torch.Tensor:
    """Smooth colour pattern [.., 3] on the plane z = PLANE_Z as a function of world (x, y)."""
    x, y = xy[..., 0], xy[..., 1]
    return torch.stack([
        0.5 + 0.4 * torch.sin(6.0 * x),
        0.5 + 0.4 * torch.cos(5.0 * y),
        0.5 + 0.3 * torch.sin(4.0 * (x + y)),
    ], dim=-1)


def camera_pose(tx: float = 0.0, ty: float = 0.0, yaw: float = 0.0, scale: float = 1.0,
                pitch: float = 0.0) -> torch.Tensor:
    """Camera-to-world Sim(3) of a camera at (tx, ty, 0) with rotation vector (pitch, yaw, 0) radians."""
    R = so3_exp(torch.tensor([pitch, yaw, 0.0], dtype=torch.float64))
    return make_sim3(R, torch.tensor([tx, ty, 0.0], dtype=torch.float64), scale)


def view(pose_c2w: torch.Tensor) -> dict:
    """Ground-truth image [H,W,3], camera-frame depth [H,W] and camera-frame points [H,W,3] of the plane.

    With a Sim(3) pose of scale s the camera-frame quantities are the world ones divided by s.
    """
    pose = pose_c2w.to(torch.float64)
    s = float(torch.linalg.det(pose[:3, :3]) ** (1 / 3))
    R, t = pose[:3, :3] / s, pose[:3, 3]
    K = intrinsics().double()
    uv = pixel_grid(WIDTH, HEIGHT, torch.float64)
    rays_cam = torch.stack([(uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1],
                            torch.ones(HEIGHT, WIDTH, dtype=torch.float64)], dim=-1)
    rays_world = rays_cam @ R.T
    lam = (PLANE_Z - t[2]) / rays_world[..., 2]  # world distance along the ray per unit camera z
    world = t + lam[..., None] * rays_world
    depth_world = lam  # camera z in world units (rays have z = 1 in the camera frame)
    return {
        "image": texture(world[..., :2]).float(),
        "depth": (depth_world / s).float(),
        "points_cam": (rays_cam * (depth_world / s)[..., None]).float(),
        "world": world.float(),
    }


def pixel_surfels(pose_c2w: torch.Tensor, footprint: float = 0.8) -> Surfels:
    """Per-pixel camera-frame surfels of the plane: the frontend's ideal output for this view."""
    v = view(pose_c2w)
    pose = pose_c2w.to(torch.float64)
    s = float(torch.linalg.det(pose[:3, :3]) ** (1 / 3))
    R_cw = (pose[:3, :3] / s).T
    n = HEIGHT * WIDTH
    q_plane_cam = rotmat_to_quat(R_cw).float()  # plane's frame (normal = world z) seen from the camera
    depth = v["depth"].reshape(n)
    return Surfels(
        means=v["points_cam"].reshape(n, 3),
        quats=q_plane_cam.expand(n, 4).clone(),
        scales=(footprint * depth / FOCAL)[:, None].expand(n, 2).clone(),
        opacities=torch.full((n,), 0.95),
        colors=v["image"].reshape(n, 3),
        keyframe_ids=torch.zeros(n, dtype=torch.int64),
    )


def voxelized_surfels(pose_c2w: torch.Tensor, keyframe_id: int = 0) -> Surfels:
    """The per-pixel surfels merged into 2x2 blocks (a quarter of the count; scales doubled to keep coverage)."""
    g = pixel_surfels(pose_c2w)
    grid = {k: v.reshape(HEIGHT, WIDTH, *v.shape[1:]) for k, v in g.tensors().items() if k != "keyframe_ids"}
    return voxelize(**grid, keyframe_id=keyframe_id, merged_scale_factor=2.0).surfels


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.clamp(0, 1) - b) ** 2).mean())
    return -10 * math.log10(max(mse, 1e-12))
