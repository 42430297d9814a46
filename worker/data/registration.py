"""Depth registered to the colour camera, and misregistration detected when the session does not say how.

Real RGB-D sensors (Kinect v1, RealSense without alignment, Azure Kinect) see depth from a second camera a few
centimetres beside the colour one, with its own intrinsics: pixel (i, j) of the depth image is not pixel (i, j) of
the colour image, and colours smear onto the wrong surfaces. With the depth camera's intrinsics and the
depth-to-colour extrinsic (what the RealSense and Azure Kinect SDKs report), `register_depth` moves every depth
pixel into the colour image: unprojected with the depth intrinsics, moved by the extrinsic, projected with the
colour intrinsics onto the nearest colour pixel, the nearest surface kept where several land (z-buffer). Pixels
nothing lands on stay 0 (unknown): small holes are left, never invented.

Without them, `MisregistrationDetector` compares the edges of depth with the edges of colour over the first frames:
the image shift that puts the depth discontinuities on the strongest colour gradients should be (0, 0); a clearly
better score elsewhere means colour and depth are not registered, which the session then reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worker.events import DepthMisregistered
from worker.geometry import Intrinsics


def register_depth(depth: np.ndarray, depth_camera: Intrinsics, color_camera: Intrinsics,
                   depth_to_color: np.ndarray) -> np.ndarray:
    """Depth [H_d, W_d] (metres, 0 = unknown) of the depth camera seen from the colour camera: float32
    [color_camera.height, color_camera.width], 0 where no depth pixel lands (see the module docstring).
    depth_to_color: 4x4 rigid transform taking depth-camera points to colour-camera points (metres)."""
    depth = np.asarray(depth, np.float32)
    if depth.shape != (depth_camera.height, depth_camera.width):
        raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but its intrinsics are for "
                         f"{depth_camera.width}x{depth_camera.height}")
    rows, cols = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[rows, cols]  # float32 throughout: sub-millimetre at 10 m, half the memory traffic of float64
    x = (cols.astype(np.float32) + np.float32(0.5 - depth_camera.cx)) * np.float32(1.0 / depth_camera.fx) * z
    y = (rows.astype(np.float32) + np.float32(0.5 - depth_camera.cy)) * np.float32(1.0 / depth_camera.fy) * z
    T = np.asarray(depth_to_color, np.float32)
    xc, yc, zc = (T[i, 0] * x + T[i, 1] * y + T[i, 2] * z + T[i, 3] for i in range(3))  # no BLAS for 3x3
    ahead = zc > 1e-6
    xc, yc, zc = xc[ahead], yc[ahead], zc[ahead]
    u = np.floor(xc / zc * np.float32(color_camera.fx) + np.float32(color_camera.cx)).astype(np.int64)
    v = np.floor(yc / zc * np.float32(color_camera.fy) + np.float32(color_camera.cy)).astype(np.int64)
    inside = (u >= 0) & (u < color_camera.width) & (v >= 0) & (v < color_camera.height)
    target = v[inside] * color_camera.width + u[inside]
    # z-buffer in one sort: key = target pixel (high bits) | depth's float32 bits (positive floats order as their
    # bits), so each pixel's nearest depth comes first among its keys
    depth_bits = zc[inside].view(np.uint32).astype(np.int64)
    keys = np.sort((target << 32) | depth_bits)
    pixel = keys >> 32
    first = np.ones(keys.size, bool)
    first[1:] = pixel[1:] != pixel[:-1]
    out = np.zeros(color_camera.height * color_camera.width, np.float32)
    out[pixel[first]] = (keys[first] & 0xFFFFFFFF).astype(np.uint32).view(np.float32)
    return out.reshape(color_camera.height, color_camera.width)


@dataclass(frozen=True)
class Misregistration:
    """What the edge comparison found: the shift (dx, dy) in pixels that best puts depth edges on colour edges,
    the agreement there and at (0, 0) (mean normalised colour gradient on depth edges), and the verdict."""

    shift: tuple[int, int]
    score: float
    score_at_zero: float
    edges: int
    misregistered: bool

    def to_event(self) -> DepthMisregistered:
        return DepthMisregistered(
            shift_px=[int(self.shift[0]), int(self.shift[1])], shift_dx=int(self.shift[0]), shift_dy=int(self.shift[1]),
            agreement=round(self.score, 4), agreement_unshifted=round(self.score_at_zero, 4),
            message=f"depth edges fit the colour edges best {self.shift[0]:+d} px across and {self.shift[1]:+d} px "
                    "down: colour and depth are not registered; give the session depth_camera (depth intrinsics and "
                    "the depth-to-colour extrinsic)")


def _colour_gradient(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(np.asarray(image, np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    magnitude = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    return magnitude / max(float(magnitude.mean()), 1e-6)  # 1 = an average pixel


def _depth_edges(depth: np.ndarray, jump: float) -> np.ndarray:
    """Depth discontinuities: both pixels of every neighbouring pair whose depths differ by more than `jump` of the
    nearer one (holes are neither side of an edge)."""
    d = np.asarray(depth, np.float32)
    valid = np.isfinite(d) & (d > 0)
    edges = np.zeros(d.shape, bool)
    for a, b, va, vb, ea, eb in (
            (d[:-1, :], d[1:, :], valid[:-1, :], valid[1:, :], edges[:-1, :], edges[1:, :]),
            (d[:, :-1], d[:, 1:], valid[:, :-1], valid[:, 1:], edges[:, :-1], edges[:, 1:])):
        step = va & vb & (np.abs(a - b) > jump * np.minimum(a, b))
        ea |= step
        eb |= step
    return edges


MIN_SHIFT_PX = 2  # the smallest best shift that counts as a misregistration


class MisregistrationDetector:
    """Accumulates, over the first `frames` frames with depth, how well depth edges shifted by (dx, dy) fall on
    colour edges, for every shift within `max_shift` pixels; `verdict()` then names the best shift. A shift of at
    least `MIN_SHIFT_PX` that beats (0, 0) by `margin` (relative) is a misregistration."""

    def __init__(self, frames: int = 5, max_shift: int = 6, margin: float = 0.15, edge_jump: float = 0.05) -> None:
        self.frames, self.max_shift, self.margin, self.edge_jump = frames, max_shift, margin, edge_jump
        self.seen = 0
        self.edges = 0
        size = 2 * max_shift + 1
        self._sums = np.zeros((size, size))

    @property
    def done(self) -> bool:
        return self.seen >= self.frames

    def add(self, image: np.ndarray, depth: np.ndarray) -> None:
        """Score one frame (image uint8 [H,W,3], depth [H,W] at the image's size)."""
        m = self.max_shift
        gradient = _colour_gradient(image)
        edges = _depth_edges(depth, self.edge_jump)
        edges[:m, :] = edges[-m:, :] = False
        edges[:, :m] = edges[:, -m:] = False
        rows, cols = np.nonzero(edges)
        if rows.size < 50:  # a flat view says nothing
            return
        for dy in range(-m, m + 1):
            for dx in range(-m, m + 1):
                self._sums[dy + m, dx + m] += float(gradient[rows + dy, cols + dx].sum())
        self.edges += int(rows.size)
        self.seen += 1

    def verdict(self) -> Misregistration | None:
        """The best shift and whether it means misregistration; None before any frame had depth edges."""
        if self.edges == 0:
            return None
        m = self.max_shift
        scores = self._sums / self.edges
        dy, dx = np.unravel_index(int(np.argmax(scores)), scores.shape)
        best, zero = float(scores[dy, dx]), float(scores[m, m])
        shift = (int(dx - m), int(dy - m))
        # A one-pixel best shift is within what registered real sensors show (edge noise, rounding in the driver's
        # own registration: TUM's Kinect frames peak at (-1, -1)); an unregistered Kinect is off by 4-12 px at 320.
        misregistered = best > zero * (1.0 + self.margin) and max(map(abs, shift)) >= MIN_SHIFT_PX
        return Misregistration(shift, best, zero, self.edges, misregistered)
