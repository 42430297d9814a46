"""Exact little scenes for the multi-view depth tests: a textured plane facing the camera and textured
axis-aligned boxes, ray cast to RGB and z-depth from any camera-to-world pose (OpenCV axes, pixel centres at +0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


def pinhole(width: int, height: int, focal_factor: float = 0.9) -> np.ndarray:
    """K with square pixels and a centred principal point."""
    f = focal_factor * width
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def translation(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def rotation_y(degrees: float) -> np.ndarray:
    """A camera turned about its own vertical axis (no translation)."""
    a = np.radians(degrees)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    return pose


def looking_down(height: float, pitch_deg: float) -> np.ndarray:
    """Camera-to-world pose (world z up, OpenCV camera axes) at `height` above the floor z = 0, looking along +y
    and down by `pitch_deg`."""
    p = np.radians(pitch_deg)
    forward = np.array([0.0, np.cos(p), -np.sin(p)])
    right = np.array([1.0, 0.0, 0.0])
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    pose[:3, 3] = (0.0, 0.0, height)
    return pose


def texture(seed: int, size: int = 256) -> np.ndarray:
    """Smooth random grey levels in [0, 1], tiling (wrapped at the borders)."""
    noise = np.random.default_rng(seed).random((size, size)).astype(np.float32)
    blurred = cv2.GaussianBlur(np.tile(noise, (3, 3)), (0, 0), 1.2)[size:2 * size, size:2 * size]
    return (blurred - blurred.min()) / np.ptp(blurred)


@dataclass
class Scene:
    """A plane z = plane_depth (world) and boxes [(min xyz, max xyz)], textured with `texel` world units per texel
    (scale every length by the same factor to test unit independence). textured=False paints everything grey."""

    plane_depth: float = 2.0
    boxes: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    texel: float = 0.01
    textured: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        self._tex = texture(self.seed)

    def _shade(self, a: np.ndarray, b: np.ndarray, offset: int) -> np.ndarray:
        if not self.textured:
            return np.full(a.shape, 0.5, np.float32)
        n = self._tex.shape[0]
        u = np.mod(a / self.texel + offset, n - 1)
        v = np.mod(b / self.texel + 2 * offset, n - 1)
        img = cv2.remap(self._tex, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_WRAP)
        return 0.15 + 0.7 * img

    def render(self, pose: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """(RGB uint8 [H, W, 3], z-depth float32 [H, W]) seen from camera-to-world `pose`."""
        xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays_cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], axis=-1)
        R, origin = pose[:3, :3], pose[:3, 3]
        dirs = rays_cam @ R.T  # world directions; t along them is the camera z-depth
        t_best = np.full(xs.shape, np.inf)
        grey = np.zeros(xs.shape, np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.plane_depth - origin[2]) / dirs[..., 2]
        hit = np.isfinite(t) & (t > 0)
        points = origin + np.where(hit, t, 0.0)[..., None] * dirs
        t_best = np.where(hit, t, t_best)
        grey = np.where(hit, self._shade(points[..., 0], points[..., 1], 0), grey)
        for k, (lo, hi) in enumerate(self.boxes):
            with np.errstate(divide="ignore", invalid="ignore"):
                t0, t1 = (np.asarray(lo) - origin) / dirs, (np.asarray(hi) - origin) / dirs
            near, far = np.minimum(t0, t1), np.maximum(t0, t1)
            enter, leave = np.nanmax(near, axis=-1), np.nanmin(far, axis=-1)
            hit = (enter <= leave) & (enter > 0) & (enter < t_best)
            axis = np.nanargmax(near, axis=-1)
            points = origin + np.where(hit, enter, 0.0)[..., None] * dirs
            a = np.where(axis == 0, points[..., 1], points[..., 0])
            b = np.where(axis == 2, points[..., 1], points[..., 2])
            t_best = np.where(hit, enter, t_best)
            grey = np.where(hit, self._shade(a, b, 37 * (k + 1)), grey)
        rgb = np.clip(grey * 255 + 0.5, 0, 255).astype(np.uint8)
        depth = np.where(np.isfinite(t_best), t_best, 0.0).astype(np.float32)
        return np.repeat(rgb[..., None], 3, axis=-1), depth


def visible_in(points_depth: np.ndarray, ref_pose: np.ndarray, pose: np.ndarray, K: np.ndarray,
               view_depth: np.ndarray, tol: float = 0.01) -> np.ndarray:
    """bool [H, W]: the reference pixels whose true surface point (depth `points_depth`) the view at `pose` sees
    (inside its image and not hidden behind something nearer in `view_depth`)."""
    H, W = points_depth.shape
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1) * points_depth[..., None]
    world = cam @ ref_pose[:3, :3].T + ref_pose[:3, 3]
    inv = np.linalg.inv(pose)
    other = world @ inv[:3, :3].T + inv[:3, 3]
    z = other[..., 2]
    u = K[0, 0] * other[..., 0] / np.where(z > 0, z, 1) + K[0, 2]
    v = K[1, 1] * other[..., 1] / np.where(z > 0, z, 1) + K[1, 2]
    inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    col, row = np.clip(u.astype(int), 0, W - 1), np.clip(v.astype(int), 0, H - 1)
    return inside & (np.abs(view_depth[row, col] - z) < tol * z)


def engine_keyframe_depths(images: list[np.ndarray], poses: list[np.ndarray], K: np.ndarray, planes=None,
                           borders=None, every: int = 4) -> list[tuple[int, np.ndarray]]:
    """(keyframe id, surfel z-depth [H, W], 0 where no surfel) of every `every`-th frame, as the engine's keyframe
    depth builds it for posed RGB (multi-view stereo, propagation, with `planes` / `borders` settings)."""
    from worker.depth import MultiViewDepthConfig
    from worker.pipeline.depth_sources import MultiViewDepth, StereoBuilder

    builder = StereoBuilder(MultiViewDepthConfig(), propagate=True, planes=planes, borders=borders)
    source = MultiViewDepth(None, buffer_frames=16, frames_after=4, builder=builder)
    depths = []
    for i, image in enumerate(images):
        source.add_frame(i, image)
        if i % every == 0:
            source.add_keyframe_at(i, K, None)
        for job in source.ready_jobs(lambda j: poses[j], force=i == len(images) - 1):
            _, grid, _ = builder.build(job)
            depths.append((job.kf_id, np.where(grid["valid"].numpy(), grid["means"][..., 2].numpy(), 0.0)))
    return depths
