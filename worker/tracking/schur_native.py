"""The compiled observation-pair sum of bundle adjustment's reduced camera system (csrc/schur_pairs.cpp through
`worker.native`, run without the GIL): the fast path of `bundle_adjustment._pair_blocks_reference`, equal up to the
order of the sums. `available()` is False and `load_error()` says why when it cannot be built."""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from worker.native import NativeLibrary

SOURCE = Path(__file__).parent / "csrc" / "schur_pairs.cpp"


def _declare(lib: ctypes.CDLL) -> None:
    p = ctypes.c_void_p
    lib.schur_subtract_pairs.argtypes = [ctypes.c_int64, p, p, p, p, p, p, ctypes.c_int64, p]
    lib.schur_subtract_pairs.restype = None


_native = NativeLibrary("schur_pairs", SOURCE, _declare)


def available() -> bool:
    """True when the kernel compiled (or was cached) and loaded."""
    return _native.available()


def load_error() -> str | None:
    """Why the kernel is unavailable (None when it loaded or was not tried yet)."""
    return _native.error


def subtract_pairs(S: np.ndarray, pair_i: np.ndarray, pair_j: np.ndarray, pair_a: np.ndarray, pair_b: np.ndarray,
                   Y: np.ndarray, W: np.ndarray) -> None:
    """S [6 F, 6 F] (C-contiguous float64, in place) -= Y[i] W[j]^T in block (a, b) for each pair (i, j, a, b)."""
    library = _native.require("Schur kernel")
    assert S.flags.c_contiguous and S.dtype == np.float64
    index = [np.ascontiguousarray(a, np.int64) for a in (pair_i, pair_j, pair_a, pair_b)]
    Y, W = np.ascontiguousarray(Y, np.float64), np.ascontiguousarray(W, np.float64)
    library.schur_subtract_pairs(len(index[0]), *(a.ctypes.data for a in index), Y.ctypes.data, W.ctypes.data,
                                 S.shape[0] // 6, S.ctypes.data)
