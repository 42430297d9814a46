"""The kernel chain of one keyframe: cost volume, view fusion, semi-global aggregation and decision, on the compiled
kernels (or the numpy reference), with the large intermediate arrays reused between calls of a thread."""

from __future__ import annotations

import logging
import threading
import time
from types import ModuleType

import numpy as np

from . import mvs_cpu, reference
from .config import MultiViewDepthConfig
from .decide import Decision, decide
from .sweep import ViewGeometry, reference_stats

log = logging.getLogger(__name__)
_workspace = threading.local()  # per calling thread: the large intermediate buffers, reused while shapes match
_fallback_logged = False


def _kernels(backend: str) -> tuple[str, ModuleType]:
    """The kernel module for config.backend; "auto" falls back to the reference (saying so once per process)."""
    global _fallback_logged
    if backend == "reference":
        return "reference", reference
    if mvs_cpu.available():
        return "cpu", mvs_cpu
    if backend == "cpu":
        raise RuntimeError(f"compiled MVS kernels unavailable: {mvs_cpu.load_error()}")
    if not _fallback_logged:
        _fallback_logged = True
        log.warning("compiled MVS kernels unavailable (%s); using the numpy reference", mvs_cpu.load_error())
    return "reference", reference


def _array(name: str, shape: tuple[int, ...], keep: bool) -> np.ndarray:
    """A float32 array of this shape: this thread's kept one when it fits, else a new one (kept when `keep`)."""
    array = getattr(_workspace, name, None)
    if array is None or array.shape != shape:
        array = np.empty(shape, dtype=np.float32)
    setattr(_workspace, name, array if keep else None)
    return array


def sweep(ref: np.ndarray, views: np.ndarray, geometries: list[ViewGeometry], planes: np.ndarray,
          config: MultiViewDepthConfig, timings: dict[str, float]) -> tuple[str, Decision]:
    """(backend used, per-pixel decision) for the grey reference ref [H, W] and views [N, H, W] seen through
    `geometries`, swept over the inverse depths `planes`; records the stages' seconds in `timings`."""
    backend, kernels = _kernels(config.backend)
    (h, w), N, D = ref.shape, len(geometries), len(planes)
    keep, threads = config.keep_buffers, config.threads

    tick = time.perf_counter()
    ref_sum, ref_ssd = reference_stats(ref, config.window_radius)
    A, b = np.stack([g.A for g in geometries]), np.stack([g.b for g in geometries])
    cost = kernels.cost_volume(ref, ref_sum, ref_ssd, views, A, b, planes, config.window_radius,
                               config.min_texture_std ** 2, threads, out=_array("cost", (N, D, h, w), keep))
    timings["cost"] = time.perf_counter() - tick

    tick = time.perf_counter()
    fused, view_min = kernels.fuse_views(cost, config.views_per_pixel, threads, out=_array("fused", (h, w, D), keep))
    workers = min(threads, config.sgm_paths)
    total = kernels.sgm(fused, config.sgm_p1, config.sgm_p2, config.sgm_paths, threads,
                        out=_array("total", (h, w, D), keep), scratch=_array("scratch", (workers - 1, h, w, D), keep))
    timings["aggregate"] = time.perf_counter() - tick

    tick = time.perf_counter()
    terms = kernels.decide_terms(total, fused, cost, view_min, config.support_margin, config.max_view_cost, threads)
    result = decide(terms, planes, config)
    timings["decide"] = time.perf_counter() - tick
    return backend, result
