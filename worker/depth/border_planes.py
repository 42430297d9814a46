"""Depth for textureless regions no plane reaches, from the supported points along their border.

A plain wall above a skirting board gets confident multi-view depth only along the board: the board's points lie
near a line, so `PlaneMemory` cannot take them for a plane, and the wall's image region holds no supported pixel
for `fill_from_planes` to match. The supported points just outside such a region (its border ring) lie where the
region's surface meets its neighbours, and indoor surfaces stand at right angles to the dominant planes or run
parallel to them. For every large image region with little support, the hypotheses, per dominant plane of the map
(normal n), are
- parallel: the plane of normal n through the ring points (a table top over the floor, whose edges all around
  are seen: the inliers must span a plane, not a line), unless it is that
  dominant plane itself: a region cut off from the floor by an edge, holding none of its own support, is not
  taken for more floor (a plain wall seen only where it meets the floor stands on it);
- perpendicular: the plane containing n through the ring points (a wall standing on the floor), tried only where
  the ring lies close to that dominant plane (`junction`): a wall is trusted where it is seen meeting the floor,
  not above any horizontal edge (a roof line against the sky).
The hypotheses of the dominant plane that orients the one holding the most ring points (within `tolerance` of
their depth) are rivals when they hold nearly as many (`ambiguity`); the closest fit (median residual) is taken
when it holds `min_inliers` of the ring and its inliers span the ring, unless a rival fits nearly as closely
(`distinct_fit`) and puts the region elsewhere (`disagreement`). The region's holes then take the plane's depth,
never beyond the supported depths' range or at grazing angles; its few supported pixels far off the plane
(`stray`: chance matches on a textureless surface, no edge parts them from it) take the plane too. Every
tolerance is relative to depth (any pose scale).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worker.depth.world_planes import (
    Plane,
    PlaneSettings,
    camera_rays,
    image_regions,
    plane_depth,
    spans_a_plane,
    world_points,
)


@dataclass(frozen=True)
class BorderSettings:
    """Which regions are completed from their border, and how sure the border's plane must be."""

    min_region: float = 0.01  # a region at least this share of the image ...
    max_support: float = 0.1  # ... with at most this share of its pixels supported
    ring: int = 5  # the border ring: supported pixels within this many pixels outside the region
    min_points: int = 30  # ring points needed
    tolerance: float = 0.02  # a ring point lies on a hypothesis within this fraction of its depth
    min_inliers: float = 0.8  # share of the ring points on the plane taken
    ambiguity: float = 0.6  # hypotheses of one dominant plane holding this share of the most inliers are rivals
    distinct_fit: float = 2.0  # the rival with the closest fit wins when the others' median residual is this times
    disagreement: float = 0.1  # its; else, if they put most region pixels this far apart (relative): no fill
    junction: float = 0.2  # perpendicular: the ring's median distance to the dominant plane, fraction of depth
    min_span: float = 0.05  # the inliers' largest image std, as a share of the image's longer side
    min_extent: float = 0.2  # parallel: the inliers' spread across / along their longest direction (not a line)
    iterations: int = 64  # RANSAC samples of the perpendicular plane's direction
    min_incidence: float = 0.1  # |cos| of the angle between a pixel's ray and the plane's normal
    depth_margin: float = 1.5  # filled depth at most this times the supported depths' 99th percentile ...
    near_margin: float = 4.0  # ... and at least their 1st percentile over this (a wall may come close)
    close_radius: int = 2  # edge pixels this close to a filled region take its plane too
    stray: float = 0.06  # a region's supported pixels this far (relative) off its border plane take the plane


def _parallel(points: np.ndarray, tol: np.ndarray, normal: np.ndarray) -> tuple[Plane, np.ndarray]:
    """The plane of `normal` through most of `points` (a median start refined on its inliers) and its inliers."""
    heights = points @ normal
    offset = -float(np.median(heights))
    inliers = np.abs(heights + offset) <= tol
    if inliers.any():
        offset = -float(np.median(heights[inliers]))
        inliers = np.abs(heights + offset) <= tol
    return Plane(normal, offset, 0.0), inliers


def _perpendicular(points: np.ndarray, tol: np.ndarray, up: np.ndarray, rng: np.random.Generator,
                   iterations: int) -> tuple[Plane, np.ndarray] | None:
    """The plane containing direction `up` through most of `points` (2-point RANSAC on the points seen along `up`,
    refined by a line fit of the inliers) and its inliers; None when no two points span a direction."""
    flat = points - np.outer(points @ up, up)
    best, best_count, anchor = None, 0, 0
    for a, b in rng.integers(0, len(points), (iterations, 2)):
        along = flat[b] - flat[a]
        normal = np.cross(up, along)
        norm = np.linalg.norm(normal)
        if norm < 1e-12:
            continue
        normal /= norm
        count = int((np.abs((points - points[a]) @ normal) <= tol).sum())
        if count > best_count:
            best, best_count, anchor = normal, count, a
    if best is None:
        return None
    offset = -float(points[anchor] @ best)
    inliers = np.abs(points @ best + offset) <= tol
    if inliers.sum() >= 2:  # refit the line of the inliers seen along `up`
        line = flat[inliers] - flat[inliers].mean(0)
        direction = np.linalg.svd(line, full_matrices=False)[2][0]
        normal = np.cross(up, direction)
        if np.linalg.norm(normal) > 1e-9:
            best = normal / np.linalg.norm(normal)
            offset = -float(np.median(points[inliers] @ best))
            inliers = np.abs(points @ best + offset) <= tol
    return Plane(best, offset, 0.0), inliers


def _depth_along(plane: Plane, centre: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """z-depth at which world `rays` [m, 3] (camera z = 1) from `centre` meet `plane` (inf where they do not)."""
    along = rays @ plane.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -(plane.normal @ centre + plane.offset) / along
    return np.where(np.isfinite(z) & (z > 0), z, np.inf)


def border_plane(points: np.ndarray, depths: np.ndarray, pixels: np.ndarray, dominant: list[Plane],
                 centre: np.ndarray, region_rays: np.ndarray, image_side: int, settings: BorderSettings,
                 seed: int = 0) -> Plane | None:
    """The plane of a region's border ring (world `points` [n, 3] seen at `depths` [n] from `pixels` [n, 2]), or
    None when no hypothesis is sure; `centre`, `region_rays`: the camera centre and the world rays (z = 1) of the
    region's pixels, on which competing hypotheses must agree; see the module docstring."""
    if len(points) < settings.min_points or not dominant:
        return None
    rng = np.random.default_rng(seed)
    tol = settings.tolerance * depths
    hypotheses: list[tuple[int, Plane, np.ndarray]] = []  # (which dominant plane orients it, plane, inliers)
    for index, plane in enumerate(dominant):
        gap = np.abs(points @ plane.normal + plane.offset) / depths
        parallel = _parallel(points, tol, plane.normal)
        if (abs(parallel[0].offset - plane.offset) > settings.tolerance * float(np.median(depths))
                and parallel[1].sum() >= 3
                and spans_a_plane(np.linalg.eigvalsh(np.cov(points[parallel[1]].T)), settings.min_extent)):
            hypotheses.append((index, *parallel))  # (the dominant plane itself is fill_from_planes' to give)
        if np.median(gap) <= settings.junction:
            found = _perpendicular(points, tol, plane.normal, rng, settings.iterations)
            if found is not None:
                hypotheses.append((index, *found))
    if not hypotheses:
        return None
    counts = np.array([inliers.sum() for _, _, inliers in hypotheses])
    if counts.max() < settings.min_inliers * len(points):
        return None
    oriented_by = hypotheses[int(counts.argmax())][0]
    # The same dominant plane's hypotheses that hold nearly as many ring points: the closer fit wins.
    rivals = [i for i, (index, _, _) in enumerate(hypotheses)
              if index == oriented_by and counts[i] >= settings.ambiguity * counts.max()]
    residual = {i: float(np.median(np.abs(points @ hypotheses[i][1].normal + hypotheses[i][1].offset) / depths))
                for i in rivals}
    best = min(rivals, key=residual.__getitem__)
    _, plane, inliers = hypotheses[best]
    if counts[best] < settings.min_inliers * len(points):
        return None
    spread = np.sqrt(np.linalg.eigvalsh(np.cov(pixels[inliers].T.astype(np.float64)))[-1])
    if spread < settings.min_span * image_side:
        return None
    z = _depth_along(plane, centre, region_rays)
    for i in rivals:
        if i != best and residual[i] < settings.distinct_fit * residual[best]:
            differ = np.abs(_depth_along(hypotheses[i][1], centre, region_rays) - z) > settings.disagreement * z
            if np.mean(differ) > 0.5:
                return None
    return plane


def fill_from_borders(depth: np.ndarray, image: np.ndarray, dominant: list[Plane], pose: np.ndarray, K: np.ndarray,
                      settings: BorderSettings | None = None,
                      regions: tuple[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W] float32 with the holes of weakly supported regions filled from their border's plane, filled
    bool [H, W]: those holes, and the regions' supported pixels off the plane, which it replaces) for a keyframe
    at camera-to-world `pose` with supported depth `depth` (> 0) and image `image` (uint8 RGB); `dominant`: the
    map's planes (world coordinates) that orient the hypotheses; `regions`: the image's regions when the caller
    has them (`image_regions`)."""
    settings = settings or BorderSettings()
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    support = depth > 0
    filled = np.zeros(depth.shape, bool)
    if not dominant or support.sum() < settings.min_points or support.all():
        return depth, filled
    edges = PlaneSettings()  # the same image regions as the dominant planes' fill
    count, labels = regions if regions is not None else image_regions(image, edges.edge_low, edges.edge_high)
    near, far = np.percentile(depth[support], [1, 99])
    near, far = near / settings.near_margin, far * settings.depth_margin
    sizes = np.bincount(labels.ravel(), minlength=count)
    supported = np.bincount(labels[support], minlength=count)
    weak = (sizes >= settings.min_region * depth.size) & (supported <= settings.max_support * sizes)
    weak[0] = False  # the edges
    kernel = np.ones((2 * settings.ring + 1,) * 2, np.uint8)
    rays = camera_rays(K, depth.shape)
    out = depth.copy()
    for label in np.flatnonzero(weak):
        region = labels == label
        ring = (cv2.dilate(region.astype(np.uint8), kernel) > 0) & support & ~region
        if ring.sum() < settings.min_points:
            continue
        ring_depth = np.where(ring, depth, 0)
        points, depths = world_points(ring_depth, pose, K)
        rows, cols = np.nonzero(ring_depth > 0)
        region_rays = rays[region] @ pose[:3, :3].T
        plane = border_plane(points, depths, np.column_stack([cols, rows]), dominant, pose[:3, 3], region_rays,
                             max(depth.shape), settings, seed=int(label))
        if plane is None:
            continue
        z = plane_depth(plane, pose, K, depth.shape, settings.min_incidence)
        on_plane_range = (z >= near) & (z <= far) & ~filled
        reach = on_plane_range & ~support
        # The region's few supported pixels off its plane are stereo's chance matches on a textureless surface
        # (no edge separates them from it): the plane replaces them.
        stray = region & support & on_plane_range & (np.abs(depth - z) > settings.stray * z)
        take = (region & reach) | stray
        if settings.close_radius > 0 and take.any():
            grown = cv2.dilate(take.astype(np.uint8), np.ones((2 * settings.close_radius + 1,) * 2, np.uint8)) > 0
            take |= grown & (labels == 0) & reach
        out[take] = z[take]
        filled |= take
    return out, filled
