"""`estimate_depth`: a keyframe's depth and confidence from neighbouring frames with known poses."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .config import MultiViewDepthConfig
from .pipeline import sweep
from .sweep import ViewGeometry, inverse_depths, pose_problem, sweep_pixels, view_geometry

log = logging.getLogger(__name__)


@dataclass
class DepthEstimate:
    """depth: float32 [H, W] in the reference camera's (pose) units, 0 where not confident. confidence: float32
    [H, W] in [0, 1], 0 exactly where depth is 0 (a failed check or below `min_confidence`). support: int16 [H, W]
    views agreeing with the depth. views_used: indices into the given neighbours that took part. depth_range: the
    (near, far) swept."""

    depth: np.ndarray
    confidence: np.ndarray
    support: np.ndarray
    views_used: list[int] = field(default_factory=list)
    depth_range: tuple[float, float] | None = None
    backend: str = "none"
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def mask(self) -> np.ndarray:
        """bool [H, W]: pixels with a confident depth."""
        return self.depth > 0

    @property
    def coverage(self) -> float:
        """Fraction of pixels with a confident depth."""
        return float(self.mask.mean())


def _empty(shape: tuple[int, int], reason: str, *args) -> DepthEstimate:
    log.warning("estimate_depth: " + reason + "; no depth for this keyframe", *args)
    return DepthEstimate(np.zeros(shape, np.float32), np.zeros(shape, np.float32), np.zeros(shape, np.int16))


def _check_inputs(ref_image: np.ndarray, K: np.ndarray, neighbours: Sequence) -> None:
    if ref_image.dtype != np.uint8 or ref_image.ndim != 3 or ref_image.shape[2] != 3:
        raise ValueError(f"ref_image must be uint8 [H, W, 3], got {ref_image.dtype} {ref_image.shape}")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite 3x3 intrinsics matrix with positive focal lengths, got {K.tolist()}")
    for i, item in enumerate(neighbours):
        if len(item) != 2:
            raise ValueError(f"neighbour {i} must be (image, pose)")
        image = np.asarray(item[0])
        if image.shape != ref_image.shape or image.dtype != np.uint8:
            raise ValueError(f"neighbour {i} image must be uint8 {ref_image.shape}, got {image.dtype} {image.shape}")


def _grey(image: np.ndarray, scale: float) -> np.ndarray:
    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    if scale == 1.0:
        return grey
    H, W = grey.shape
    return cv2.resize(grey, (max(8, round(W * scale)), max(8, round(H * scale))), interpolation=cv2.INTER_AREA)


def _usable(neighbours: Sequence) -> list[int]:
    """Indices of the neighbours whose pose can be used (the others are skipped with a warning)."""
    usable = []
    for i, (_, pose) in enumerate(neighbours):
        if (problem := pose_problem(np.asarray(pose, dtype=np.float64))) is not None:
            log.warning("estimate_depth: neighbour %d skipped: %s", i, problem)
        else:
            usable.append(i)
    return usable


def _with_parallax(indices: list[int], poses: list[np.ndarray], ref_pose: np.ndarray, K: np.ndarray,
                   shape: tuple[int, int], depth_range: tuple[float, float],
                   config: MultiViewDepthConfig) -> tuple[list[int], list[ViewGeometry]]:
    """The neighbours (indices, geometries) whose epipolar segment over the range is long enough to measure depth
    (in full-resolution pixels); the others are dropped with a warning."""
    kept, geometries = [], []
    h, w = shape
    for i, pose in zip(indices, poses, strict=True):
        geometry = view_geometry(K, ref_pose, pose)
        extent = sweep_pixels(geometry, w, h, *depth_range) / config.scale
        if extent < config.min_sweep_pixels:
            log.warning("estimate_depth: neighbour %d dropped: its epipolar sweep is %.2f px (no baseline or pure "
                        "rotation)", i, extent)
            continue
        kept.append(i)
        geometries.append(geometry)
    return kept, geometries


def _default_range(baselines: list[float], config: MultiViewDepthConfig) -> tuple[float, float] | None:
    median = float(np.median(baselines))
    if not median > 0:
        return None
    return median * config.near_over_baseline, median * config.far_over_baseline


def estimate_depth(ref_image: np.ndarray, K: np.ndarray, ref_pose: np.ndarray,
                   neighbours: Sequence[tuple[np.ndarray, np.ndarray]],
                   depth_range: tuple[float, float] | None = None,
                   config: MultiViewDepthConfig | None = None) -> DepthEstimate:
    """Depth and confidence of `ref_image` from `neighbours` [(image, camera-to-world pose)] of the same camera K.

    Plane sweep over `config.num_hypotheses` inverse depths in depth_range (None: multiples of the median
    baseline), ZNCC costs fused over the best views, semi-global aggregation, parabola refinement, and a
    consistency check that keeps pixels at least `min_views` views agree on. Degenerate input (no neighbour, no
    baseline, pure rotation, NaN poses, textureless images) gives zero or few confident pixels and a warning; malformed
    arrays raise ValueError. At most `config.num_views` neighbours are used (the first ones).
    """
    config = config or MultiViewDepthConfig()
    ref_image, K = np.asarray(ref_image), np.asarray(K, dtype=np.float64)
    _check_inputs(ref_image, K, neighbours)
    shape = ref_image.shape[:2]
    ref_pose = np.asarray(ref_pose, dtype=np.float64)
    if (problem := pose_problem(ref_pose)) is not None:
        return _empty(shape, "keyframe pose unusable (%s)", problem)
    if depth_range is not None:
        near, far = (float(v) for v in depth_range)
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
            raise ValueError(f"depth_range must be finite with 0 < near < far, got {depth_range}")
    usable = _usable(neighbours)[: config.num_views]
    if not usable:
        return _empty(shape, "no usable neighbour (%d given)", len(neighbours))
    poses = [np.asarray(neighbours[i][1], dtype=np.float64) for i in usable]
    if depth_range is None:
        depth_range = _default_range([float(np.linalg.norm(p[:3, 3] - ref_pose[:3, 3])) for p in poses], config)
        if depth_range is None:
            return _empty(shape, "neighbours have no baseline (pure rotation or a still camera)")
    near, far = depth_range

    started = time.perf_counter()
    scale = config.scale
    Ks = np.diag([scale, scale, 1.0]) @ K
    ref = _grey(ref_image, scale)
    kept, geometries = _with_parallax(usable, poses, ref_pose, Ks, ref.shape, (near, far), config)
    if len(kept) < config.min_views:
        return _empty(shape, "%d neighbour(s) with parallax, fewer than min_views = %d", len(kept), config.min_views)
    views = np.stack([_grey(neighbours[i][0], scale) for i in kept])
    timings = {"prepare": time.perf_counter() - started}
    planes = inverse_depths(near, far, config.num_hypotheses)
    backend, result = sweep(ref, views, geometries, planes, config, timings)

    tick = time.perf_counter()
    confidence, support = result.confidence, result.support
    depth = np.where(result.ok, 1.0 / np.maximum(result.inv_depth, 1e-12), 0.0).astype(np.float32)
    if scale != 1.0:
        size = (shape[1], shape[0])
        depth, confidence, support = (cv2.resize(a, size, interpolation=cv2.INTER_NEAREST)
                                      for a in (depth, confidence, support))
    timings["decide"] += time.perf_counter() - tick
    timings["total"] = time.perf_counter() - started
    estimate = DepthEstimate(depth, confidence, support.astype(np.int16), kept, (float(near), float(far)), backend,
                             timings)
    if estimate.coverage < config.warn_below_coverage:
        log.warning("estimate_depth: only %.2f%% of pixels confident (textureless, occluded or too little parallax)",
                    100 * estimate.coverage)
    return estimate
