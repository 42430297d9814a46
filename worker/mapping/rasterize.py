"""Differentiable 2DGS (surfel) rasterizer: one entry point, three backends.

`rasterize(surfels, viewmat, K, width, height)` renders colour, expected depth, accumulation and normals.
Backends: "cpu" (compiled C++ forward/backward kernels, `raster_cpu`; falls back to the reference with a logged
warning when it cannot be compiled), "reference" (pure torch, `raster_reference`; the test oracle; any device),
"gsplat" (CUDA, `gsplat.rasterization_2dgs`), "auto" (CPU tensors: cpu; CUDA tensors: gsplat when it imports, else
the reference).

Conventions (gsplat 1.5.3's, so CPU and GPU images agree up to float summation order):
- OpenCV camera (x right, y down, z forward); viewmat = world->camera 4x4; K = 3x3 pixel intrinsics; pixel (row i,
  column j) has its centre at (j + 0.5, i + 0.5).
- Surfel k: ray transform T = K [s_u R_c[:,0] | s_v R_c[:,1] | mu_c]; the pixel ray meets the surfel plane at (u, v)
  (see `raster_projection`); rho = min(u^2 + v^2, 2 |x - c|^2) with c the centre of the r = 1 conic's bounding box
  (object-space low-pass filter); alpha = min(0.999, o exp(-rho / 2)); pairs with alpha < 1/255 are skipped.
- Culled: centre depth <= 0.01 (near) or >= 1e10 (far), degenerate conics, boxes off-screen. Per-axis radius
  ceil(3.33 h) of the r = 1 conic's half extent h; a surfel is evaluated on every pixel of the 16x16 tiles its box
  touches (gsplat's tile rule), sorted front to back by centre depth.
- Compositing: T starts at 1; a surfel whose next T = T (1 - alpha) would be <= 1e-4 ends the pixel and is not added.
  w = alpha T; colour = sum w c + T_final background; alpha = 1 - T_final; depth = sum w z / max(alpha, 1e-10)
  with z the surfel's centre depth (gsplat's "ED"); normals = sum w n, n the camera-facing surfel normal, rotated to
  the world frame, unnormalised.
Gradients flow to every surfel attribute and to viewmat (not to K).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import torch

from .raster_projection import project_surfels
from .raster_reference import composite_reference
from .surfels import Surfels

logger = logging.getLogger(__name__)

BACKENDS = ("auto", "cpu", "reference", "gsplat")
_warned_fallback = False


class RenderResult(NamedTuple):
    rgb: torch.Tensor  # [H, W, 3] colour composited over the background
    depth: torch.Tensor  # [H, W] expected depth, 0 where nothing was hit
    alpha: torch.Tensor  # [H, W] accumulation 1 - T_final
    normals: torch.Tensor  # [H, W, 3] sum of w n in the world frame, unnormalised


def _check_inputs(surfels: Surfels, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                  background: torch.Tensor | None, backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; expected one of {BACKENDS}")
    if not isinstance(surfels, Surfels):
        raise ValueError(f"surfels must be a Surfels, got {type(surfels).__name__}")
    if not torch.is_tensor(viewmat) or tuple(viewmat.shape) != (4, 4):
        raise ValueError(f"viewmat must be a 4x4 tensor, got {getattr(viewmat, 'shape', type(viewmat))}")
    if not torch.is_tensor(K) or tuple(K.shape) != (3, 3):
        raise ValueError(f"K must be a 3x3 tensor, got {getattr(K, 'shape', type(K))}")
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive integers, got {width}x{height}")
    if background is not None and (not torch.is_tensor(background) or tuple(background.shape) != (3,)):
        raise ValueError(f"background must be a tensor of shape (3,), got {getattr(background, 'shape', None)}")
    for name, t in (("viewmat", viewmat), ("K", K)):
        if t.device != surfels.device:
            raise ValueError(f"{name} is on {t.device} but the surfels are on {surfels.device}")
        if not torch.isfinite(t.detach()).all():
            raise ValueError(f"{name} has non-finite entries")


def _choose_backend(backend: str, device: torch.device) -> str:
    if backend != "auto":
        return backend
    if device.type == "cuda":
        from . import raster_gsplat

        # without gsplat, the pure-torch reference still runs on the GPU; the compiled kernels are CPU-only
        return "gsplat" if raster_gsplat.available() else "reference"
    return "cpu"


def rasterize(surfels: Surfels, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
              background: torch.Tensor | None = None, backend: str = "auto") -> RenderResult:
    """Render surfels into a width x height camera with world->camera `viewmat` and intrinsics `K`."""
    _check_inputs(surfels, viewmat, K, width, height, background, backend)
    width, height = int(width), int(height)
    dtype, device = surfels.means.dtype, surfels.device
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else background.to(dtype)
    viewmat, K = viewmat.to(dtype), K.to(dtype)
    backend = _choose_backend(backend, device)
    if backend == "gsplat":
        from .raster_gsplat import rasterize_gsplat

        features, alpha = rasterize_gsplat(surfels, viewmat, K, width, height)
    elif backend == "cpu" and _compiled_available():
        from .raster_cpu import rasterize_cpu

        return RenderResult(*rasterize_cpu(surfels.means, surfels.quats, surfels.scales, surfels.opacities,
                                           surfels.colors, viewmat, K, width, height, bg))
    else:
        features, alpha = _composite_reference(surfels, viewmat, K, width, height)
    rgb = features[..., :3] + (1.0 - alpha)[..., None] * bg
    depth = features[..., 3] / alpha.clamp_min(1e-10)
    normals = features[..., 4:7] @ viewmat[:3, :3]  # camera -> world: R_cw^T n
    return RenderResult(rgb, depth, alpha, normals)


def visible_mask(surfels: Surfels, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[N] bool: the surfels a render from this camera can touch (the rasterizer's own culling rule: centre depth,
    degenerate conic, screen box). Rendering only these gives the same image and the same gradients."""
    _check_inputs(surfels, viewmat, K, width, height, None, "auto")
    dtype = surfels.means.dtype
    viewmat, K = viewmat.detach().to(dtype), K.detach().to(dtype)
    if surfels.device.type == "cpu":
        from . import raster_cpu

        if raster_cpu.available():
            return raster_cpu.visible_cpu(surfels.means, surfels.quats, surfels.scales, surfels.opacities,
                                          surfels.colors, viewmat, K, int(width), int(height))
    with torch.no_grad():
        ids = project_surfels(surfels.means, surfels.quats, surfels.scales, viewmat, K, int(width), int(height)).ids
    mask = torch.zeros(len(surfels), dtype=torch.bool, device=surfels.device)
    mask[ids] = True
    return mask


def _compiled_available() -> bool:
    """Whether the compiled CPU path loaded; logs the fallback to the reference once."""
    from . import raster_cpu

    if raster_cpu.available():
        return True
    global _warned_fallback
    if not _warned_fallback:
        logger.warning("compiled CPU rasterizer unavailable (%s); using the pure-torch reference",
                       raster_cpu.load_error())
        _warned_fallback = True
    return False


def _composite_reference(surfels: Surfels, viewmat: torch.Tensor, K: torch.Tensor, width: int,
                         height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum w [colour, depth, camera normal] [H, W, 7], alpha [H, W]) with the pure-torch reference."""
    proj = project_surfels(surfels.means, surfels.quats, surfels.scales, viewmat, K, width, height)
    opacities = surfels.opacities[proj.ids]
    features = torch.cat([surfels.colors[proj.ids], proj.depths[:, None], proj.normals], dim=-1)
    return composite_reference(proj.uv_planes, proj.means2d, opacities, features, proj.radii, proj.depths,
                               width, height)
