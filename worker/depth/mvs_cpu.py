"""Compiled plane-sweep kernels (csrc/mvs_cpu.cpp through `worker.native`): the fast path of `reference`.

Same signatures and results as `worker.depth.reference` (up to float rounding); `available()` is False and
`load_error()` says why when the library cannot be built, and callers then use the reference.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from worker.native import DEFAULT_FLAGS, NativeLibrary

from .decide import DecisionTerms

SOURCE = Path(__file__).parent / "csrc" / "mvs_cpu.cpp"
# lets min reductions vectorise; the kernels never see NaN or infinity (inputs are checked, costs are bounded)
FLAGS = (*DEFAULT_FLAGS, "-fno-math-errno", "-fno-trapping-math", "-ffinite-math-only", "-fno-signed-zeros")


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    lib.mvs_cost_volume.argtypes = [i32, i32, i32, i32, p, p, p, p, p, p, p, i32, f32, i32, p]
    lib.mvs_fuse_views.argtypes = [i32, i32, i64, p, i32, i32, p, p]
    lib.mvs_sgm.argtypes = [i32, i32, i32, p, f32, f32, i32, i32, p, p]
    lib.mvs_decide_terms.argtypes = [i32, i32, i64, p, p, p, p, f32, f32, i32, p, p, p, p, p, p]
    for fn in (lib.mvs_cost_volume, lib.mvs_fuse_views, lib.mvs_sgm, lib.mvs_decide_terms):
        fn.restype = None


_native = NativeLibrary("mvs_cpu", SOURCE, _declare, FLAGS)


def available() -> bool:
    """True when the kernels compiled (or were cached) and loaded."""
    return _native.available()


def load_error() -> str | None:
    """Why the kernels are unavailable (None when they loaded or were not tried yet)."""
    return _native.error


def _lib() -> ctypes.CDLL:
    return _native.require("MVS kernels")


def _c(a: np.ndarray, dtype) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


def _out(out: np.ndarray | None, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
    """`out` when it is a C-contiguous array of this shape and dtype (reused: no page faults), else a new one."""
    if out is not None and out.shape == shape and out.dtype == dtype and out.flags.c_contiguous:
        return out
    return np.empty(shape, dtype=dtype)


def cost_volume(ref: np.ndarray, ref_sum: np.ndarray, ref_ssd: np.ndarray, views: np.ndarray, A: np.ndarray,
                b: np.ndarray, inv_depths: np.ndarray, radius: int, min_var: float, threads: int = 1,
                out: np.ndarray | None = None) -> np.ndarray:
    """1 - ZNCC of each view warped onto each plane, float32 [N, D, H, W]; -1 where the view misses the pixel.
    Written into `out` when it fits."""
    N, H, W = views.shape
    D = len(inv_depths)
    inputs = [_c(ref, np.float32), _c(ref_sum, np.float32), _c(ref_ssd, np.float32), _c(views, np.float32),
              _c(A, np.float64), _c(b, np.float64), _c(inv_depths, np.float64)]
    out = _out(out, (N, D, H, W))
    _lib().mvs_cost_volume(H, W, N, D, *(_ptr(a) for a in inputs), int(radius), float(min_var), int(threads),
                           _ptr(out))
    return out


def fuse_views(cost: np.ndarray, keep: int, threads: int = 1,
               out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(fused [H, W, D] (into `out` when it fits), view_min [N, H, W]) as `reference.fuse_views`."""
    N, D, H, W = cost.shape
    cost = _c(cost, np.float32)
    fused = _out(out, (H, W, D))
    view_min = np.empty((N, H, W), dtype=np.float32)
    _lib().mvs_fuse_views(N, D, H * W, _ptr(cost), int(keep), int(threads), _ptr(fused), _ptr(view_min))
    return fused, view_min


def sgm(cost: np.ndarray, p1: float, p2: float, paths: int, threads: int = 1, out: np.ndarray | None = None,
        scratch: np.ndarray | None = None) -> np.ndarray:
    """Sum over `paths` directions of the semi-global path costs of cost [H, W, D], float32 [H, W, D] (into `out`
    when it fits; `scratch`: [threads - 1, H, W, D] per-thread partial sums, reused when it fits)."""
    H, W, D = cost.shape
    cost = _c(cost, np.float32)
    total = _out(out, cost.shape)
    workers = max(1, min(int(threads), int(paths)))
    scratch = _out(scratch, (workers - 1, H, W, D))
    _lib().mvs_sgm(H, W, D, _ptr(cost), float(p1), float(p2), int(paths), int(threads), _ptr(total), _ptr(scratch))
    return total


def decide_terms(total: np.ndarray, fused: np.ndarray, cost: np.ndarray, view_min: np.ndarray, margin: float,
                 max_cost: float, threads: int = 1) -> DecisionTerms:
    """Per-pixel decision terms as `reference.decide_terms`."""
    H, W, D = total.shape
    N = cost.shape[0]
    inputs = [_c(total, np.float32), _c(fused, np.float32), _c(cost, np.float32), _c(view_min, np.float32)]
    terms = DecisionTerms(index=np.empty((H, W)), interior=np.empty((H, W), dtype=bool),
                          uniqueness=np.empty((H, W), dtype=np.float32), margin=np.empty((H, W), dtype=np.float32),
                          photometric=np.empty((H, W), dtype=np.float32), support=np.empty((H, W), dtype=np.int16))
    _lib().mvs_decide_terms(N, D, H * W, *(_ptr(a) for a in inputs), float(margin), float(max_cost), int(threads),
                            _ptr(terms.index), _ptr(terms.interior), _ptr(terms.uniqueness), _ptr(terms.margin),
                            _ptr(terms.photometric), _ptr(terms.support))
    return terms
