"""The kernel chain of one keyframe: cost volume, view fusion, semi-global aggregation and decision, on the compiled
kernels (or the numpy reference), with the large intermediate arrays reused between calls."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from types import ModuleType

import numpy as np

from . import mvs_cpu, reference
from .config import MultiViewDepthConfig
from .decide import Decision, decide
from .sweep import ViewGeometry, reference_stats

log = logging.getLogger(__name__)
_fallback_logged = False
KEPT_WORKSPACES = 2  # sets of buffers kept between calls (concurrent calls beyond this allocate their own)


class _Workspaces:
    """Sets of large float32 buffers: a call borrows one (or gets an empty one) and gives it back afterwards; at most
    KEPT_WORKSPACES sets stay allocated between calls, so many sessions' threads do not each hold one."""

    def __init__(self) -> None:
        self._free: list[dict[str, np.ndarray]] = []
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def borrow(self, keep: bool) -> Iterator[dict[str, np.ndarray]]:
        with self._lock:
            workspace = self._free.pop() if keep and self._free else {}
        try:
            yield workspace
        finally:
            if keep:
                with self._lock:
                    if len(self._free) < KEPT_WORKSPACES:
                        self._free.append(workspace)


_workspaces = _Workspaces()


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


def _array(workspace: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    """The workspace's float32 array `name` when it has this shape, else a new one (stored in the workspace)."""
    array = workspace.get(name)
    if array is None or array.shape != shape:
        array = workspace[name] = np.empty(shape, dtype=np.float32)
    return array


def sweep(ref: np.ndarray, views: np.ndarray, geometries: list[ViewGeometry], planes: np.ndarray,
          config: MultiViewDepthConfig, timings: dict[str, float]) -> tuple[str, Decision]:
    """(backend used, per-pixel decision) for the grey reference ref [H, W] and views [N, H, W] seen through
    `geometries`, swept over the inverse depths `planes`; records the stages' seconds in `timings`."""
    backend, kernels = _kernels(config.backend)
    with _workspaces.borrow(config.keep_buffers) as workspace:
        return backend, _chain(kernels, workspace, ref, views, geometries, planes, config, timings)


def _chain(kernels: ModuleType, workspace: dict[str, np.ndarray], ref: np.ndarray, views: np.ndarray,
           geometries: list[ViewGeometry], planes: np.ndarray, config: MultiViewDepthConfig,
           timings: dict[str, float]) -> Decision:
    (h, w), N, D, threads = ref.shape, len(geometries), len(planes), config.threads

    tick = time.perf_counter()
    ref_sum, ref_ssd = reference_stats(ref, config.window_radius)
    A, b = np.stack([g.A for g in geometries]), np.stack([g.b for g in geometries])
    cost = kernels.cost_volume(ref, ref_sum, ref_ssd, views, A, b, planes, config.window_radius,
                               config.min_texture_std ** 2, threads, out=_array(workspace, "cost", (N, D, h, w)))
    timings["cost"] = time.perf_counter() - tick

    tick = time.perf_counter()
    fused, view_min = kernels.fuse_views(cost, config.views_per_pixel, threads,
                                         out=_array(workspace, "fused", (h, w, D)))
    workers = min(threads, config.sgm_paths)
    total = kernels.sgm(fused, config.sgm_p1, config.sgm_p2, config.sgm_paths, threads,
                        out=_array(workspace, "total", (h, w, D)),
                        scratch=_array(workspace, "scratch", (workers - 1, h, w, D)))
    timings["aggregate"] = time.perf_counter() - tick

    tick = time.perf_counter()
    terms = kernels.decide_terms(total, fused, cost, view_min, config.support_margin, config.max_view_cost, threads)
    result = decide(terms, planes, config)
    timings["decide"] = time.perf_counter() - tick
    return result
