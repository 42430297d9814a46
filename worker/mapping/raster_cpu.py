"""Compiled CPU compositor (C++ forward and backward kernels, OpenMP over tiles) behind a torch.autograd.Function.

`csrc/raster_cpu.cpp` has a plain C ABI and no torch headers, so the first use compiles it in a few seconds with
the system C++ compiler ($CXX, default c++; -O3 -fopenmp) into $FLASHMONO_EXT_DIR (default
~/.cache/flashmono/torch_extensions), keyed by a hash of the source, flags and compiler; later uses load the cached
library. Python owns every buffer and calls the kernels through ctypes (the GIL is released during a call). If the
build fails, `available()` is False, `load_error()` says why, and `rasterize` falls back to the pure-torch reference.
Same inputs and outputs as `raster_reference.composite_reference`; float32 and float64.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import tempfile
import threading
from pathlib import Path

import torch

from .raster_tiles import tile_grid

SOURCE = Path(__file__).parent / "csrc" / "raster_cpu.cpp"
CXX_FLAGS = ["-O3", "-std=c++17", "-fPIC", "-shared", "-fopenmp"]
_PAIR_FIXED = 12  # per-pair gradient columns before the features: dA(3) dB(3) dC(3) dmeans2d(2) dopacity(1)

_lock = threading.Lock()
_library: ctypes.CDLL | None = None
_error: str | None = None
_tried = False


def extension_dir() -> Path:
    """Where the compiled library is cached."""
    return Path(os.environ.get("FLASHMONO_EXT_DIR", Path.home() / ".cache" / "flashmono" / "torch_extensions"))


def _compiler() -> list[str]:
    return os.environ.get("CXX", "c++").split()


def _build() -> Path:
    """Compile the kernels unless a library for this exact source, flags and compiler is cached; its path."""
    compiler = _compiler()
    version = subprocess.run([*compiler, "--version"], capture_output=True, text=True, check=True).stdout
    key = hashlib.sha256(SOURCE.read_bytes() + " ".join(CXX_FLAGS).encode() + version.encode()).hexdigest()[:16]
    target = extension_dir() / f"flashmono_raster_cpu_{key}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        result = subprocess.run([*compiler, *CXX_FLAGS, str(SOURCE), "-o", tmp], capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"compiling {SOURCE.name} failed:\n{result.stderr[-4000:]}")
        os.replace(tmp, target)  # atomic: concurrent builders never see a half-written library
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    for suffix in ("f32", "f64"):
        getattr(lib, f"raster_bin_count_{suffix}").restype = i64
        getattr(lib, f"raster_bin_count_{suffix}").argtypes = [p, p, i64, i32, i32, p, p]
        getattr(lib, f"raster_bin_fill_{suffix}").argtypes = [p, p, p, i64, i32, i32, p, p, p, p]
        getattr(lib, f"raster_reach_rects_{suffix}").argtypes = [p, p, p, i64, i32, i32, i32, p]
        getattr(lib, f"raster_forward_{suffix}").argtypes = [p, p, p, p, p, p, p, i32, i32, i32, i32, p, p, p]
        getattr(lib, f"raster_backward_{suffix}").argtypes = [p, p, p, p, p, p, p, p, p, i64, i32, i32, i32, i32,
                                                              p, p, p, p, p, p, p, p, p]
        for name in ("bin_fill", "reach_rects", "forward", "backward"):
            getattr(lib, f"raster_{name}_{suffix}").restype = None


def _load() -> ctypes.CDLL | None:
    global _library, _error, _tried
    with _lock:
        if not _tried:
            _tried = True
            try:
                library = ctypes.CDLL(str(_build()))
                _declare(library)
                _library = library
            except Exception as exc:  # no compiler, build error, unloadable library...
                _error = f"{type(exc).__name__}: {exc}"
        return _library


def available() -> bool:
    """True when the kernels compiled (or were cached) and loaded."""
    return _load() is not None


def load_error() -> str | None:
    """Why the kernels are unavailable (None when they loaded or were not tried yet)."""
    return _error


def _kernel(name: str, dtype: torch.dtype):
    suffix = {torch.float32: "f32", torch.float64: "f64"}.get(dtype)
    if suffix is None:
        raise ValueError(f"the compiled CPU rasterizer supports float32 and float64, not {dtype}")
    return getattr(_library, f"raster_{name}_{suffix}")


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, planes, means2d, opacities, features, rays, radii, order, width, height):
        dtype, M, F = planes.dtype, planes.shape[0], features.shape[1]
        threads = torch.get_num_threads()
        tiles_x, tiles_y = tile_grid(width, height)
        tile_offsets = torch.empty(tiles_x * tiles_y + 1, dtype=torch.int64)
        surfel_offsets = torch.empty(M + 1, dtype=torch.int64)
        n_pairs = _kernel("bin_count", dtype)(_ptr(means2d), _ptr(radii), M, width, height, _ptr(tile_offsets),
                                              _ptr(surfel_offsets))
        pair_surfel = torch.empty(n_pairs, dtype=torch.int32)
        surfel_pairs = torch.empty(n_pairs, dtype=torch.int64)
        _kernel("bin_fill", dtype)(_ptr(means2d), _ptr(radii), _ptr(order), M, width, height, _ptr(tile_offsets),
                                   _ptr(surfel_offsets), _ptr(pair_surfel), _ptr(surfel_pairs))
        rects = torch.empty(M, 4, dtype=torch.int32)
        _kernel("reach_rects", dtype)(_ptr(rays), _ptr(means2d), _ptr(opacities), M, width, height, threads,
                                      _ptr(rects))
        out_feat = torch.empty(height, width, F, dtype=dtype)
        T_final = torch.empty(height, width, dtype=dtype)
        counts = torch.empty(height, width, dtype=torch.int32)
        _kernel("forward", dtype)(_ptr(tile_offsets), _ptr(pair_surfel), _ptr(rects), _ptr(planes), _ptr(means2d),
                                  _ptr(opacities), _ptr(features), F, width, height, threads, _ptr(out_feat),
                                  _ptr(T_final), _ptr(counts))
        ctx.save_for_backward(planes, means2d, opacities, features, T_final, counts, tile_offsets, pair_surfel,
                              surfel_offsets, surfel_pairs, rects)
        ctx.size = (width, height)
        ctx.mark_non_differentiable(T_final)
        return out_feat, 1.0 - T_final

    @staticmethod
    def backward(ctx, g_feat, g_alpha):
        width, height = ctx.size
        (planes, means2d, opacities, features, T_final, counts, tile_offsets, pair_surfel, surfel_offsets,
         surfel_pairs, rects) = ctx.saved_tensors
        dtype, M, F = planes.dtype, planes.shape[0], features.shape[1]
        g_feat = g_feat.to(dtype).contiguous()
        g_alpha = g_alpha.to(dtype).contiguous()
        pair_grads = torch.zeros(pair_surfel.shape[0], _PAIR_FIXED + F, dtype=dtype)
        d_planes, d_means2d = torch.empty_like(planes), torch.empty_like(means2d)
        d_opac, d_feat = torch.empty_like(opacities), torch.empty_like(features)
        _kernel("backward", dtype)(
            _ptr(tile_offsets), _ptr(pair_surfel), _ptr(surfel_offsets), _ptr(surfel_pairs), _ptr(rects),
            _ptr(planes), _ptr(means2d), _ptr(opacities), _ptr(features), M, F, width, height,
            torch.get_num_threads(), _ptr(T_final), _ptr(counts), _ptr(g_feat), _ptr(g_alpha), _ptr(pair_grads),
            _ptr(d_planes), _ptr(d_means2d), _ptr(d_opac), _ptr(d_feat))
        return d_planes, d_means2d, d_opac, d_feat, None, None, None, None, None


def composite_cpu(uv_planes: torch.Tensor, ray_transforms: torch.Tensor, means2d: torch.Tensor,
                  opacities: torch.Tensor, features: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor,
                  width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum_i w_i f_i [H, W, F], alpha [H, W]) like `composite_reference`, with the compiled kernels."""
    if not available():
        raise RuntimeError(f"compiled CPU rasterizer unavailable: {_error}")
    if uv_planes.device.type != "cpu":
        raise ValueError(f"the compiled CPU rasterizer needs CPU tensors, got {uv_planes.device}")
    dtype = uv_planes.dtype
    order = torch.sort(depths.detach(), stable=True).indices
    return _Composite.apply(
        uv_planes.reshape(-1, 9).contiguous(), means2d.contiguous(), opacities.to(dtype).contiguous(),
        features.to(dtype).contiguous(), ray_transforms.detach().reshape(-1, 9).to(dtype).contiguous(),
        radii.to(torch.int32).contiguous(), order.contiguous(), int(width), int(height))
