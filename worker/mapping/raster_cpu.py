"""Compiled CPU rasterizer: projection, tile binning, compositing and the backward of all three in C++, behind
torch.autograd.Functions; `worker_threads()` threads (torch.get_num_threads() unless `using_threads` says otherwise).

`rasterize_cpu` is the fast path `rasterize(backend="cpu")` uses: one forward call chain from surfel attributes to
the composited [colour, depth, camera normal] channels, one backward chain to the gradients of means, quats, scales,
opacities, colours and the view matrix. `composite_cpu` runs the compositing stage alone on already projected
surfels (the stage `raster_reference.composite_reference` implements in torch); `visible_cpu` is the culling rule.

`csrc/raster_cpu.cpp` has a plain C ABI and no torch headers, so the first use compiles it in a few seconds with
the system C++ compiler ($CXX, default c++; -O3 -pthread) into $FLASHMONO_EXT_DIR (default
~/.cache/flashmono/torch_extensions), keyed by a hash of the source, flags and compiler; later uses load the cached
library. Python owns every buffer and calls the kernels through ctypes (the GIL is released during a call). If the
build fails, `available()` is False, `load_error()` says why, and `rasterize` falls back to the pure-torch reference.
float32 and float64; results and gradients are bitwise independent of the thread count.
"""

from __future__ import annotations

import contextlib
import ctypes
import threading
from pathlib import Path
from typing import NamedTuple

import torch

from worker.native import DEFAULT_FLAGS, NativeLibrary, extension_dir

from .raster_tiles import tile_grid

SOURCE = Path(__file__).parent / "csrc" / "raster_cpu.cpp"
CXX_FLAGS = list(DEFAULT_FLAGS)
_PAIR_FIXED = 12  # per-pair gradient columns before the features: dA(3) dB(3) dC(3) dmeans2d(2) dopacity(1)

_threads = threading.local()  # per calling thread: the kernels' thread count while `using_threads` is active
__all__ = ["available", "composite_cpu", "extension_dir", "load_error", "rasterize_cpu", "using_threads",
           "visible_cpu", "worker_threads"]


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.raster_projected_features.restype = i32
    lib.raster_projected_features.argtypes = []
    lib.raster_build_surfel_index.restype = None
    lib.raster_build_surfel_index.argtypes = [p, i64, i64, p, p]
    for suffix in ("f32", "f64"):
        signatures = {
            "project": [i64, p, p, p, p, p, p, p, i32, i32, i32, p, p, p, p, p, p, p],
            "project_backward": [i64, p, p, p, p, p, p, p, p, p, i32, p, p, p, p, p],
            "finish": [i64, p, p, p, p, i32, p, p, p, p],
            "finish_backward": [i64, p, p, p, p, p, p, p, p, i32, p, p, p, p],
            "bin_count": [p, p, i64, i32, i32, p],
            "bin_fill": [p, p, p, i64, i32, i32, i32, p, p],
            "reach_rects": [p, p, p, i64, i32, i32, i32, p],
            "forward": [p, p, p, p, p, p, p, i32, i32, i32, i32, p, p, p],
            "backward": [p, p, p, p, p, p, p, p, p, i64, i32, i32, i32, i32, p, p, p, p, p, p, p, p, p],
        }
        for name, argtypes in signatures.items():
            fn = getattr(lib, f"raster_{name}_{suffix}")
            fn.argtypes = argtypes
            fn.restype = i64 if name == "bin_count" else None


_native = NativeLibrary("raster_cpu", SOURCE, _declare, CXX_FLAGS)


def _load() -> ctypes.CDLL | None:
    return _native.load()


def worker_threads() -> int:
    """Threads the kernels use: torch.get_num_threads(), or the count set by `using_threads` in this thread."""
    return getattr(_threads, "count", None) or torch.get_num_threads()


@contextlib.contextmanager
def using_threads(count: int):
    """Run the kernels on `count` threads inside the block (this calling thread only), whatever torch uses."""
    if count < 1:
        raise ValueError(f"thread count must be >= 1, got {count}")
    previous = getattr(_threads, "count", None)
    _threads.count = int(count)
    try:
        yield
    finally:
        _threads.count = previous


def available() -> bool:
    """True when the kernels compiled (or were cached) and loaded."""
    return _load() is not None


def load_error() -> str | None:
    """Why the kernels are unavailable (None when they loaded or were not tried yet)."""
    return _native.error


def _kernel(name: str, dtype: torch.dtype):
    suffix = {torch.float32: "f32", torch.float64: "f64"}.get(dtype)
    if suffix is None:
        raise ValueError(f"the compiled CPU rasterizer supports float32 and float64, not {dtype}")
    return getattr(_native.library, f"raster_{name}_{suffix}")


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


class _Binned(NamedTuple):
    """Tile lists and the forward state the backward pass needs."""

    tile_offsets: torch.Tensor  # [tiles + 1] int64
    pair_surfel: torch.Tensor  # [P] int32, per tile front to back
    T_final: torch.Tensor  # [H, W] transmittance left after the last contributor
    counts: torch.Tensor  # [H, W] int32 list entries up to the last contributor


def _bin_and_composite(planes, means2d, opacities, features, radii, depths, rects, width, height):
    """Tile binning and the forward compositing: (sum w f [H, W, F], binning state)."""
    dtype, N, F = planes.dtype, planes.shape[0], features.shape[1]
    threads = worker_threads()
    tiles_x, tiles_y = tile_grid(width, height)
    tile_offsets = torch.empty(tiles_x * tiles_y + 1, dtype=torch.int64)
    n_pairs = _kernel("bin_count", dtype)(_ptr(means2d), _ptr(radii), N, width, height, _ptr(tile_offsets))
    pair_surfel = torch.empty(n_pairs, dtype=torch.int32)
    _kernel("bin_fill", dtype)(_ptr(means2d), _ptr(radii), _ptr(depths), N, width, height, threads,
                               _ptr(tile_offsets), _ptr(pair_surfel))
    out_feat = torch.empty(height, width, F, dtype=dtype)
    T_final = torch.empty(height, width, dtype=dtype)
    counts = torch.empty(height, width, dtype=torch.int32)
    _kernel("forward", dtype)(_ptr(tile_offsets), _ptr(pair_surfel), _ptr(rects), _ptr(planes), _ptr(means2d),
                              _ptr(opacities), _ptr(features), F, width, height, threads, _ptr(out_feat),
                              _ptr(T_final), _ptr(counts))
    return out_feat, _Binned(tile_offsets, pair_surfel, T_final, counts)


def _composite_backward(binned: _Binned, planes, means2d, opacities, features, rects, g_feat, g_alpha, width,
                        height):
    """Gradients of the compositing w.r.t. (uv planes, means2d, opacities, features), one row per surfel."""
    dtype, N, F = planes.dtype, planes.shape[0], features.shape[1]
    n_pairs = binned.pair_surfel.shape[0]
    surfel_offsets = torch.empty(N + 1, dtype=torch.int64)
    surfel_pairs = torch.empty(n_pairs, dtype=torch.int64)
    _native.library.raster_build_surfel_index(_ptr(binned.pair_surfel), n_pairs, N, _ptr(surfel_offsets),
                                       _ptr(surfel_pairs))
    pair_grads = torch.empty(n_pairs, _PAIR_FIXED + F, dtype=dtype)
    d_planes, d_means2d = torch.empty_like(planes), torch.empty_like(means2d)
    d_opac, d_feat = torch.empty_like(opacities), torch.empty_like(features)
    _kernel("backward", dtype)(
        _ptr(binned.tile_offsets), _ptr(binned.pair_surfel), _ptr(surfel_offsets), _ptr(surfel_pairs), _ptr(rects),
        _ptr(planes), _ptr(means2d), _ptr(opacities), _ptr(features), N, F, width, height,
        worker_threads(), _ptr(binned.T_final), _ptr(binned.counts), _ptr(g_feat.to(dtype).contiguous()),
        _ptr(g_alpha.to(dtype).contiguous()), _ptr(pair_grads), _ptr(d_planes), _ptr(d_means2d), _ptr(d_opac),
        _ptr(d_feat))
    return d_planes, d_means2d, d_opac, d_feat


class _Composite(torch.autograd.Function):
    """Compositing of already projected surfels (the stage `composite_reference` mirrors)."""

    @staticmethod
    def forward(ctx, planes, means2d, opacities, features, rays, radii, depths, width, height):
        rects = torch.empty(planes.shape[0], 4, dtype=torch.int32)
        _kernel("reach_rects", planes.dtype)(_ptr(rays), _ptr(means2d), _ptr(opacities), planes.shape[0], width,
                                             height, worker_threads(), _ptr(rects))
        out_feat, binned = _bin_and_composite(planes, means2d, opacities, features, radii, depths, rects, width,
                                              height)
        ctx.save_for_backward(planes, means2d, opacities, features, rects, *binned)
        ctx.size = (width, height)
        ctx.mark_non_differentiable(binned.T_final)
        return out_feat, 1.0 - binned.T_final

    @staticmethod
    def backward(ctx, g_feat, g_alpha):
        planes, means2d, opacities, features, rects, *binned = ctx.saved_tensors
        grads = _composite_backward(_Binned(*binned), planes, means2d, opacities, features, rects, g_feat, g_alpha,
                                    *ctx.size)
        return (*grads, None, None, None, None, None)


def composite_cpu(uv_planes: torch.Tensor, ray_transforms: torch.Tensor, means2d: torch.Tensor,
                  opacities: torch.Tensor, features: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor,
                  width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum_i w_i f_i [H, W, F], alpha [H, W]) like `composite_reference`, with the compiled kernels.

    A surfel with a zero radius is treated as culled.
    """
    _require(uv_planes)
    dtype = uv_planes.dtype
    return _Composite.apply(
        uv_planes.reshape(-1, 9).contiguous(), means2d.contiguous(), opacities.to(dtype).contiguous(),
        features.to(dtype).contiguous(), ray_transforms.detach().reshape(-1, 9).to(dtype).contiguous(),
        radii.to(torch.int32).contiguous(), depths.detach().to(dtype).contiguous(), int(width), int(height))


class _Rasterize(torch.autograd.Function):
    """Projection, binning, compositing and finishing in the compiled library, and the backward of all four."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, viewmat, background, K, width, height):
        dtype, N = means.dtype, means.shape[0]
        threads = worker_threads()
        F = _native.library.raster_projected_features()
        planes = torch.empty(N, 9, dtype=dtype)
        means2d, depths = torch.empty(N, 2, dtype=dtype), torch.empty(N, dtype=dtype)
        features = torch.empty(N, F, dtype=dtype)
        radii, rects = torch.empty(N, 2, dtype=torch.int32), torch.empty(N, 4, dtype=torch.int32)
        _kernel("project", dtype)(N, _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(colors),
                                  _ptr(viewmat), _ptr(K), width, height, threads, None, _ptr(planes), _ptr(means2d),
                                  _ptr(depths), _ptr(features), _ptr(radii), _ptr(rects))
        out_feat, binned = _bin_and_composite(planes, means2d, opacities, features, radii, depths, rects, width,
                                              height)
        rgb, depth = torch.empty(height, width, 3, dtype=dtype), torch.empty(height, width, dtype=dtype)
        alpha, normals = torch.empty(height, width, dtype=dtype), torch.empty(height, width, 3, dtype=dtype)
        _kernel("finish", dtype)(width * height, _ptr(out_feat), _ptr(binned.T_final), _ptr(background),
                                 _ptr(viewmat), threads, _ptr(rgb), _ptr(depth), _ptr(alpha), _ptr(normals))
        ctx.save_for_backward(means, quats, scales, opacities, viewmat, background, K, planes, means2d, features,
                              radii, rects, out_feat, *binned)
        ctx.size = (width, height)
        return rgb, depth, alpha, normals

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_alpha, g_normals):
        (means, quats, scales, opacities, viewmat, background, K, planes, means2d, features, radii, rects, out_feat,
         *binned) = ctx.saved_tensors
        binned = _Binned(*binned)
        width, height = ctx.size
        dtype, N = means.dtype, means.shape[0]
        threads = worker_threads()

        # None (an output that took no part in the loss) is passed as a null pointer: a zero gradient
        grads = [None if g is None else g.to(dtype).contiguous() for g in (g_rgb, g_depth, g_alpha, g_normals)]
        g_feat, g_alpha_total = torch.empty_like(out_feat), torch.empty(height, width, dtype=dtype)
        d_background, d_rotation = torch.empty(3, dtype=dtype), torch.empty(3, 3, dtype=dtype)
        _kernel("finish_backward", dtype)(width * height, _ptr(out_feat), _ptr(binned.T_final), _ptr(background),
                                          _ptr(viewmat), *(None if g is None else _ptr(g) for g in grads), threads,
                                          _ptr(g_feat), _ptr(g_alpha_total), _ptr(d_background), _ptr(d_rotation))
        d_planes, d_means2d, d_opac, d_feat = _composite_backward(binned, planes, means2d, opacities, features, rects,
                                                                  g_feat, g_alpha_total, width, height)
        d_means, d_quats, d_scales = torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)
        d_colors, d_viewmat = torch.empty(N, 3, dtype=dtype), torch.empty(4, 4, dtype=dtype)
        _kernel("project_backward", dtype)(N, _ptr(means), _ptr(quats), _ptr(scales), _ptr(viewmat), _ptr(K),
                                           _ptr(radii), _ptr(d_planes), _ptr(d_means2d), _ptr(d_feat), threads,
                                           _ptr(d_means), _ptr(d_quats), _ptr(d_scales), _ptr(d_colors),
                                           _ptr(d_viewmat))
        d_viewmat[:3, :3] += d_rotation
        return d_means, d_quats, d_scales, d_opac, d_colors, d_viewmat, d_background, None, None, None


def rasterize_cpu(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                  colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                  background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render surfels in one compiled pass: (rgb [H,W,3], depth [H,W], alpha [H,W], world normals [H,W,3]).

    The same values as `project_surfels`, `composite_reference` and the finishing steps `rasterize` documents.
    Differentiable w.r.t. means, quats (any norm), scales, opacities, colours, viewmat and the background; K gets
    no gradient. Runs no torch operators (whose idle OpenMP workers spin and slow a busy machine down).
    """
    _require(means)
    dtype = means.dtype
    inputs = [t.to(dtype).contiguous() for t in (means, quats, scales, opacities, colors, viewmat, background)]
    return _Rasterize.apply(*inputs, K.detach().to(dtype).contiguous(), int(width), int(height))


def visible_cpu(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[N] bool: the surfels `rasterize_cpu` would draw for this camera (its own culling, no gradients)."""
    _require(means)
    dtype, N = means.dtype, means.shape[0]
    inputs = [t.detach().to(dtype).contiguous() for t in (means, quats, scales, opacities, colors, viewmat, K)]
    planes = torch.empty(N, 9, dtype=dtype)
    means2d, depths = torch.empty(N, 2, dtype=dtype), torch.empty(N, dtype=dtype)
    features = torch.empty(N, _native.library.raster_projected_features(), dtype=dtype)
    radii, rects = torch.empty(N, 2, dtype=torch.int32), torch.empty(N, 4, dtype=torch.int32)
    _kernel("project", dtype)(N, *(_ptr(t) for t in inputs), int(width), int(height), worker_threads(), None,
                              _ptr(planes), _ptr(means2d), _ptr(depths), _ptr(features), _ptr(radii), _ptr(rects))
    return radii[:, 0] > 0


def _require(t: torch.Tensor) -> None:
    if not available():
        raise RuntimeError(f"compiled CPU rasterizer unavailable: {_native.error}")
    if t.device.type != "cpu":
        raise ValueError(f"the compiled CPU rasterizer needs CPU tensors, got {t.device}")
