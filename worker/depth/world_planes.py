"""Depth for the large textureless regions of a keyframe from the planes the map already has.

A uniform floor or wall gets confident multi-view depth only near the few textured places on it (edges, objects
standing on it), and local propagation (worker.depth.hole_fill) reaches a band around those. The places differ from
keyframe to keyframe, so the confident points of the recent keyframes together show the scene's dominant planes
(`PlaneMemory`: RANSAC in world coordinates, inliers within `tolerance` of each point's depth, a plane kept when it
holds `min_share` of the points spread in two directions). A keyframe's image is cut into regions along its edges
(low thresholds: smooth shading has no edge, a boundary between surfaces has one); a region's holes take the plane
that most of the region's supported pixels (confident or propagated) lie on, when those are `agreement` of them, at
least `min_pixels` of the image and spread in two directions: the plane is trusted only over a region that already
lies on it in this view, never beyond the supported depths' range (`depth_margin`) or at grazing angles.

Every tolerance is relative to depth, so any pose scale (monocular SLAM's) works.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np


@dataclass(frozen=True)
class PlaneSettings:
    """How planes are found in the remembered points and where a keyframe trusts them."""

    tolerance: float = 0.015  # point-to-plane distance, as a fraction of the point's depth
    min_share: float = 0.1  # a plane holds at least this share of the remembered points
    max_planes: int = 4
    min_extent: float = 0.2  # the inliers' spread across / along their longest direction (a plane, not a line)
    iterations: int = 300
    sample: int = 20_000  # points scored per RANSAC hypothesis (a random subset of the memory)
    keyframes: int = 20  # recent keyframes whose points are remembered
    stride: int = 2  # every stride-th confident pixel (both directions) is remembered
    on_tolerance: float = 0.06  # a keyframe's pixel lies on a plane within this fraction of its depth
    agreement: float = 0.6  # share of an image region's supported pixels on the plane for its holes to take it
    min_pixels: float = 0.005  # ... and those on-plane pixels at least this share of the image
    min_spread: float = 0.02  # ... spread in two directions: smallest std at least this share of the longer side
    region_extent: float = 0.2  # ... and at least this share of their largest std (a band where planes meet is not)
    edge_low: int = 5  # Canny thresholds (8-bit levels) of the edges that bound the image regions: low, so that
    edge_high: int = 15  # faint boundaries stop a plane; smooth shading has none
    min_incidence: float = 0.1  # |cos| of the angle between a pixel's ray and the plane's normal
    depth_margin: float = 1.5  # filled depth at most this times the supported depths' 99th percentile
    close_radius: int = 2  # holes this thin inside a plane's region (morphological closing) take the plane
    # A keyframe whose confident multi-view depth covers more than this keeps its own (and its local propagation):
    # on textured scenes the dominant planes would paint over the furniture in front of them (ICL posed RGB: depth
    # L1 4.18 -> 4.60 cm, -0.26 dB when every keyframe was filled); textureless views (the cabinet's 8-26 %) take them.
    max_coverage: float = 0.5


@dataclass(frozen=True)
class Plane:
    """Points x with normal . x + offset = 0 (world coordinates, unit normal); `share`: of the points fitted."""

    normal: np.ndarray
    offset: float
    share: float


def camera_rays(K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Camera rays (z = 1) through the pixel centres, [H, W, 3]."""
    H, W = shape
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    return np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)


def world_points(depth: np.ndarray, pose: np.ndarray, K: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(world points [n, 3], their depths [n]) of the pixels of `depth` > 0 on a grid of `stride` (camera-to-world
    `pose`, depth in its units)."""
    rays = camera_rays(K, depth.shape)[::stride, ::stride]
    d = depth[::stride, ::stride]
    keep = np.isfinite(d) & (d > 0)
    cam = rays[keep] * d[keep][:, None]
    return cam @ pose[:3, :3].T + pose[:3, 3], d[keep].astype(np.float64)


def _refit(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(unit normal, offset, eigenvalues ascending) of the least-squares plane through `points`."""
    centre = points.mean(0)
    values, vectors = np.linalg.eigh(np.cov((points - centre).T))
    normal = vectors[:, 0]
    return normal, float(-normal @ centre), values


def spans_a_plane(eigenvalues: np.ndarray, min_extent: float) -> bool:
    """Whether points whose covariance has `eigenvalues` (ascending) span a plane, not a line: their second spread
    at least `min_extent` of the first."""
    return bool(np.sqrt(max(eigenvalues[1], 0.0) / max(eigenvalues[2], 1e-30)) >= min_extent)


def fit_planes(points: np.ndarray, depths: np.ndarray, settings: PlaneSettings | None = None,
               seed: int = 0) -> list[Plane]:
    """The dominant planes of `points` [n, 3] (observed at `depths` [n]), largest first; see the module docstring."""
    settings = settings or PlaneSettings()
    planes: list[Plane] = []
    total = len(points)
    if total < 3:
        return planes
    rng = np.random.default_rng(seed)
    remaining = np.ones(total, bool)
    tol = settings.tolerance * depths
    for _ in range(settings.max_planes):
        index = np.flatnonzero(remaining)
        if len(index) < max(settings.min_share * total, 3):
            break
        scored = index if len(index) <= settings.sample else rng.choice(index, settings.sample, replace=False)
        P, t = points[scored], tol[scored]
        best_count, best = 0, None
        for sample in rng.integers(0, len(P), (settings.iterations, 3)):
            a, b, c = P[sample]
            normal = np.cross(b - a, c - a)
            norm = np.linalg.norm(normal)
            if norm < 1e-12:
                continue
            normal /= norm
            count = int((np.abs(P @ normal - normal @ a) <= t).sum())
            if count > best_count:
                best_count, best = count, (normal, float(-normal @ a))
        if best is None:
            break
        inliers = remaining & (np.abs(points @ best[0] + best[1]) <= tol)
        if inliers.sum() < 3:
            break
        normal, offset, values = _refit(points[inliers])
        inliers = remaining & (np.abs(points @ normal + offset) <= tol)
        if inliers.sum() < settings.min_share * total:
            break
        remaining &= ~inliers
        if spans_a_plane(values, settings.min_extent):
            planes.append(Plane(normal, offset, float(inliers.sum() / total)))
    return planes


def plane_depth(plane: Plane, pose: np.ndarray, K: np.ndarray, shape: tuple[int, int],
                min_incidence: float = 0.0) -> np.ndarray:
    """Depth [H, W] at which each pixel's ray meets `plane` (camera-to-world `pose`); 0 where it meets it behind the
    camera, never, or at a grazing angle (|cos| below `min_incidence`)."""
    R, t = pose[:3, :3], pose[:3, 3]
    normal = R.T @ plane.normal  # the plane in camera coordinates: normal . x + offset = 0
    offset = plane.normal @ t + plane.offset
    rays = camera_rays(K, shape)
    along = rays @ normal
    cos = np.abs(along) / np.linalg.norm(rays, axis=-1)
    z = np.where(cos > max(min_incidence, 1e-9), -offset / np.where(along != 0, along, 1.0), 0.0)
    return np.where(z > 0, z, 0.0)


def image_regions(image: np.ndarray, low: int, high: int, chroma_factor: float = 3.0) -> tuple[int, np.ndarray]:
    """(count, labels [H, W]) of the 4-connected regions between the image's edges (label 0: the edges, widened by a
    pixel): Canny with thresholds `low`, `high` on the blurred lightness, and `chroma_factor` times those on the
    blurred colour-opponent channels (Lab a, b), so that surfaces of one lightness but different colours are
    separated while compression's colour noise is not an edge."""
    lab = cv2.cvtColor(cv2.GaussianBlur(image, (5, 5), 0), cv2.COLOR_RGB2LAB)
    edges = cv2.Canny(np.ascontiguousarray(lab[..., 0]), low, high)
    if chroma_factor > 0:
        for channel in (1, 2):
            edges |= cv2.Canny(np.ascontiguousarray(lab[..., channel]), chroma_factor * low, chroma_factor * high)
    edges = cv2.dilate(edges, np.ones((3, 3), np.uint8)) > 0
    return cv2.connectedComponents((~edges).astype(np.uint8), connectivity=4)


def _region_spread(regions: np.ndarray, mask: np.ndarray, count: int) -> np.ndarray:
    """Per region [count]: the smallest and the largest standard deviation (pixels, over all directions) of its
    `mask` pixels."""
    rows, cols = np.nonzero(mask)
    label = regions[rows, cols]
    n = np.maximum(np.bincount(label, minlength=count), 1)
    mu, mv = np.bincount(label, cols, count) / n, np.bincount(label, rows, count) / n
    cuu = np.bincount(label, cols * cols, count) / n - mu * mu
    cvv = np.bincount(label, rows * rows, count) / n - mv * mv
    cuv = np.bincount(label, cols * rows, count) / n - mu * mv
    half = (cuu + cvv) / 2
    root = np.sqrt(np.maximum(half ** 2 - (cuu * cvv - cuv ** 2), 0.0))
    return np.sqrt(np.maximum(half - root, 0.0)), np.sqrt(np.maximum(half + root, 0.0))


def fill_from_planes(depth: np.ndarray, image: np.ndarray, planes: list[Plane], pose: np.ndarray, K: np.ndarray,
                     settings: PlaneSettings | None = None,
                     regions: tuple[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W] float32 with holes filled from `planes`, filled bool [H, W]) for a keyframe at `pose` whose
    supported depth (> 0: confident or propagated) is `depth` and image `image` (uint8 RGB); see the module
    docstring. An image region takes the plane that most of its supported pixels lie on, when they are enough and
    spread in two directions (pixels along a line, such as where a wall meets the floor, lie on several planes)."""
    settings = settings or PlaneSettings()
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    support = depth > 0
    filled = np.zeros(depth.shape, bool)
    if not planes or support.sum() < 3 or support.all():
        return depth, filled
    far = settings.depth_margin * float(np.percentile(depth[support], 99))
    count, regions = regions if regions is not None else image_regions(image, settings.edge_low, settings.edge_high)
    supported = np.bincount(regions[support], minlength=count)
    min_pixels, min_spread = settings.min_pixels * depth.size, settings.min_spread * max(depth.shape)
    zs, ons, scores = [], [], []
    for plane in planes:
        z = plane_depth(plane, pose, K, depth.shape, settings.min_incidence)
        on = support & (z > 0) & (np.abs(depth - z) <= settings.on_tolerance * z)
        on_count = np.bincount(regions[on], minlength=count)
        agrees = (on_count >= min_pixels) & (on_count >= settings.agreement * supported)
        narrow, wide = _region_spread(regions, on, count)
        agrees &= (narrow >= min_spread) & (narrow >= settings.region_extent * wide)
        zs.append(z)
        ons.append(on)
        scores.append(np.where(agrees, on_count, 0))
    scores = np.stack(scores)
    best, chosen = scores.argmax(0), scores.max(0) > 0
    chosen[0] = False  # the edges
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.close_radius + 1,) * 2)
    out = depth.copy()
    for p, (z, on) in enumerate(zip(zs, ons, strict=True)):
        mine = (chosen & (best == p))[regions]
        reach = (z > 0) & (z <= far) & ~support & ~filled
        take = mine & reach
        if settings.close_radius > 0:  # edge pixels and specks inside the plane's regions take it too
            inside = cv2.morphologyEx((mine & (take | on)).astype(np.uint8), cv2.MORPH_CLOSE, kernel)
            take |= (inside > 0) & reach
        out[take] = z[take]
        filled |= take
    return out, filled


class PlaneMemory:
    """The confident points of the recent keyframes (world coordinates) and the planes they show."""

    def __init__(self, settings: PlaneSettings | None = None) -> None:
        self.settings = settings or PlaneSettings()
        self.points: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._planes: list[Plane] | None = None

    def add(self, kf_id: int, depth: np.ndarray, pose: np.ndarray, K: np.ndarray) -> None:
        """Remember keyframe `kf_id`'s confident `depth` (0 = none) seen from camera-to-world `pose`."""
        self.points[int(kf_id)] = world_points(depth, pose, K, self.settings.stride)
        self.points.move_to_end(int(kf_id))
        while len(self.points) > self.settings.keyframes:
            self.points.popitem(last=False)
        self._planes = None

    def planes(self) -> list[Plane]:
        """The dominant planes of the remembered points (refitted after each `add`)."""
        if self._planes is None:
            if not self.points:
                return []
            points = np.concatenate([p for p, _ in self.points.values()])
            depths = np.concatenate([d for _, d in self.points.values()])
            self._planes = fit_planes(points, depths, self.settings)
        return self._planes

    def state_dict(self) -> dict[str, Any]:
        return {"ids": list(self.points), "points": [p for p, _ in self.points.values()],
                "depths": [d for _, d in self.points.values()]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.points = OrderedDict((int(i), (np.asarray(p, np.float64).reshape(-1, 3), np.asarray(d, np.float64)))
                                  for i, p, d in zip(state["ids"], state["points"], state["depths"], strict=True))
        self._planes = None
