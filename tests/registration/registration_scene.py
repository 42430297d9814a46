"""A synthetic RGB-D rig for registration tests: fronto-parallel textured boards in front of a textured wall, seen
by a colour camera and by a depth camera beside it with its own intrinsics (ray-cast exactly)."""

from __future__ import annotations

import numpy as np

from worker.geometry import Intrinsics

# (x0, x1, y0, y1, z, base colour) in the colour camera's frame, metres; the last one is the wall
BOARDS = [(-0.5, -0.05, -0.35, 0.25, 1.2, (200, 60, 40)), (0.1, 0.6, -0.2, 0.4, 1.6, (40, 160, 210)),
          (-0.3, 0.25, 0.3, 0.6, 1.0, (230, 210, 60)), (-9.0, 9.0, -9.0, 9.0, 3.0, (120, 120, 120))]


def _texture(x: np.ndarray, y: np.ndarray, base: tuple[int, int, int], k: int) -> np.ndarray:
    """A smooth pattern (no sharp edges inside a board: the edges that matter are the boards' outlines)."""
    shade = 0.8 + 0.2 * np.sin(7.0 * x + 3.0 * k) * np.cos(5.0 * y - k)
    return np.clip(np.asarray(base, np.float64)[None, :] * shade[:, None], 0, 255)


def render(camera: Intrinsics, camera_to_colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(image uint8 [H,W,3], z-depth float32 [H,W]) seen by a camera whose pose in the colour camera's frame is
    `camera_to_colour` (4x4 rigid)."""
    h, w = camera.height, camera.width
    rows, cols = np.mgrid[0:h, 0:w]
    rays = np.stack([(cols.ravel() + 0.5 - camera.cx) / camera.fx, (rows.ravel() + 0.5 - camera.cy) / camera.fy,
                     np.ones(h * w)], axis=1)
    R, t = camera_to_colour[:3, :3], camera_to_colour[:3, 3]
    directions = rays @ R.T
    best = np.full(h * w, np.inf)
    colour = np.zeros((h * w, 3))
    for k, (x0, x1, y0, y1, z, base) in enumerate(BOARDS):
        s = (z - t[2]) / directions[:, 2]  # ray parameter where it meets the board's plane
        x, y = t[0] + s * directions[:, 0], t[1] + s * directions[:, 1]
        hit = (s > 0) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & (s < best)
        best[hit] = s[hit]
        colour[hit] = _texture(x[hit], y[hit], base, k)
    depth = best.reshape(h, w)  # the camera's z along its own axis: rays have unit z in the camera frame
    return colour.reshape(h, w, 3).round().astype(np.uint8), depth.astype(np.float32)


def rig() -> tuple[Intrinsics, Intrinsics, np.ndarray]:
    """(colour camera, depth camera, depth-to-colour extrinsic): the depth camera 5 cm to the side of the colour
    one, turned by 1 degree, with a narrower field of view and another principal point (a Kinect-like pair)."""
    colour = Intrinsics(200.0, 200.0, 80.0, 60.0, 160, 120)
    depth = Intrinsics(212.0, 211.0, 78.5, 62.0, 160, 120)
    angle = np.radians(1.0)
    depth_to_colour = np.eye(4)
    depth_to_colour[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    depth_to_colour[:3, 3] = [0.05, 0.0, 0.0]
    return colour, depth, depth_to_colour
