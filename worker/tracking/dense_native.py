"""Compiled dense-alignment kernels (csrc/dense_align.cpp through `worker.native`): the fast path of
`worker.tracking.dense_reference`, same signatures and results up to float rounding. The kernels run without the GIL
(ctypes releases it), so tracking does not hold up the mapping thread. `available()` is False and `load_error()`
says why when the library cannot be built; callers then use the reference.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from worker.native import NativeLibrary

from .dense_reference import HUBER_K, TermSystem

SOURCE = Path(__file__).parent / "csrc" / "dense_align.cpp"
_PHOTOMETRIC_OUT, _GEOMETRIC_OUT = 44, 45


class _Level(ctypes.Structure):
    """csrc/dense_align.cpp's DenseLevel: one level's reference samples and current images."""

    _fields_ = [("n_photo", ctypes.c_int64), ("P_photo", ctypes.c_void_p), ("intensity", ctypes.c_void_p),
                ("n_geo", ctypes.c_int64), ("P_geo", ctypes.c_void_p), ("depth", ctypes.c_double),
                ("K", ctypes.c_double * 4), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("iterations", ctypes.c_int64), ("grey", ctypes.c_void_p), ("grad_x", ctypes.c_void_p),
                ("grad_y", ctypes.c_void_p), ("points", ctypes.c_void_p), ("normals", ctypes.c_void_p)]


def _declare(lib: ctypes.CDLL) -> None:
    p, i32, i64, f32, f64 = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64, ctypes.c_float, ctypes.c_double
    lib.dense_points.argtypes = [i32, i32, p, p, p]
    lib.dense_normals.argtypes = [i32, i32, p, f32, p]
    lib.dense_downsample_depth.argtypes = [i32, i32, p, f64, p]
    lib.dense_photometric_system.argtypes = [i64, p, p, p, p, i32, i32, p, p, p, f64, f64, f64, i64, p]
    lib.dense_geometric_system.argtypes = [i64, p, p, p, i32, i32, p, p, f64, f64, f64, f64, i64, p]
    lib.dense_align.argtypes = [i32, p, p, i64, f64, p, p]
    for fn in (lib.dense_points, lib.dense_normals, lib.dense_downsample_depth, lib.dense_photometric_system,
               lib.dense_geometric_system, lib.dense_align):
        fn.restype = None


_native = NativeLibrary("dense_align", SOURCE, _declare)


def available() -> bool:
    """True when the kernels compiled (or were cached) and loaded."""
    return _native.available()


def load_error() -> str | None:
    """Why the kernels are unavailable (None when they loaded or were not tried yet)."""
    return _native.error


def _lib() -> ctypes.CDLL:
    return _native.require("dense-alignment kernels")


def _c(a: np.ndarray, dtype) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def _camera(K: np.ndarray) -> np.ndarray:
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64)


def downsample_depth(depth: np.ndarray, edge_ratio: float) -> np.ndarray:
    """See `dense_reference.downsample_depth`."""
    depth = _c(depth, np.float32)
    h, w = depth.shape
    out = np.empty((h // 2, w // 2), np.float32)
    _lib().dense_downsample_depth(h, w, depth.ctypes.data, float(edge_ratio), out.ctypes.data)
    return out


def points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """See `dense_reference.points`."""
    depth = _c(depth, np.float32)
    h, w = depth.shape
    out = np.empty((h, w, 3), np.float32)
    _lib().dense_points(h, w, depth.ctypes.data, _camera(K).ctypes.data, out.ctypes.data)
    return out


def normals(points: np.ndarray, edge_ratio: float) -> np.ndarray:
    """See `dense_reference.normals`."""
    points = _c(points, np.float32)
    h, w = points.shape[:2]
    out = np.empty_like(points)
    _lib().dense_normals(h, w, points.ctypes.data, float(edge_ratio), out.ctypes.data)
    return out


def photometric_system(P: np.ndarray, intensity: np.ndarray, T: np.ndarray, K: np.ndarray, grey: np.ndarray,
                       grad_x: np.ndarray, grad_y: np.ndarray, floor: float, weight: float, min_points: int
                       ) -> TermSystem:
    """See `dense_reference.photometric_system`."""
    P, intensity, T = _c(P, np.float64), _c(intensity, np.float64), _c(T, np.float64)
    grey, grad_x, grad_y = _c(grey, np.float32), _c(grad_x, np.float32), _c(grad_y, np.float32)
    h, w = grey.shape
    out = np.empty(_PHOTOMETRIC_OUT)
    _lib().dense_photometric_system(P.shape[0], P.ctypes.data, intensity.ctypes.data, T.ctypes.data,
                                    _camera(K).ctypes.data, h, w, grey.ctypes.data, grad_x.ctypes.data,
                                    grad_y.ctypes.data, float(floor), float(weight), HUBER_K, int(min_points),
                                    out.ctypes.data)
    return TermSystem(out[:36].reshape(6, 6), out[36:42], int(out[42]), float(out[43]))


def geometric_system(P: np.ndarray, T: np.ndarray, K: np.ndarray, cur_points: np.ndarray, cur_normals: np.ndarray,
                     max_association: float, floor: float, weight: float, min_points: int) -> TermSystem:
    """See `dense_reference.geometric_system`."""
    P, T = _c(P, np.float64), _c(T, np.float64)
    cur_points, cur_normals = _c(cur_points, np.float32), _c(cur_normals, np.float32)
    h, w = cur_points.shape[:2]
    out = np.empty(_GEOMETRIC_OUT)
    _lib().dense_geometric_system(P.shape[0], P.ctypes.data, T.ctypes.data, _camera(K).ctypes.data, h, w,
                                  cur_points.ctypes.data, cur_normals.ctypes.data, float(max_association),
                                  float(floor), float(weight), HUBER_K, int(min_points), out.ctypes.data)
    return TermSystem(out[:36].reshape(6, 6), out[36:42], int(out[42]), float(out[43]), int(out[44]))


def align_levels(levels: list[tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray,
                                    np.ndarray, np.ndarray, np.ndarray, int]],
                 terms: tuple[float, float, float, float, float], min_points: int, convergence: float,
                 T: np.ndarray, state: np.ndarray) -> None:
    """Gauss-Newton on every level, coarsest (last) first, in one call (one GIL release per alignment): the loop of
    `dense_alignment.solve_level` over `photometric_system` + `geometric_system`. Each level is (P_photo,
    intensity, P_geo, depth, K, grey, grad_x, grad_y, points, normals, iterations); terms = (photometric floor,
    photometric weight, max association, geometric floor, geometric weight); T [4, 4] and state = (overlap,
    photometric scale, geometric scale, points used, ok) float64 are updated in place; the levels stop at the
    first ill-posed one."""
    assert T.flags.c_contiguous and T.dtype == np.float64 and T.shape == (4, 4)
    assert state.flags.c_contiguous and state.dtype == np.float64 and state.shape == (5,)
    table = (_Level * len(levels))()
    keep = []  # the arrays the table points into, alive until the call returns
    for entry, (P_photo, intensity, P_geo, depth, K, *images, iterations) in zip(table, levels, strict=True):
        doubles = [_c(a, np.float64) for a in (P_photo, intensity, P_geo)]
        floats = [_c(a, np.float32) for a in images]
        keep += doubles + floats
        entry.n_photo, entry.P_photo, entry.intensity = len(doubles[0]), doubles[0].ctypes.data, doubles[1].ctypes.data
        entry.n_geo, entry.P_geo, entry.depth = len(doubles[2]), doubles[2].ctypes.data, float(depth)
        entry.K[:] = _camera(K).tolist()
        entry.h, entry.w = floats[0].shape
        entry.iterations = int(iterations)
        entry.grey, entry.grad_x, entry.grad_y, entry.points, entry.normals = (a.ctypes.data for a in floats)
    weights = np.array([*terms, HUBER_K], np.float64)
    _lib().dense_align(len(levels), ctypes.addressof(table), weights.ctypes.data, int(min_points),
                       float(convergence), T.ctypes.data, state.ctypes.data)
