"""GPU backend: gsplat 1.5.3's `rasterization_2dgs` (CUDA only), returning what the CPU compositors return."""

from __future__ import annotations

import torch

from .surfels import Surfels


def available() -> bool:
    """True when CUDA is present and gsplat imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def rasterize_gsplat(surfels: Surfels, viewmat: torch.Tensor, K: torch.Tensor, width: int,
                     height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum w [colour, depth, camera normal] [H, W, 7], alpha [H, W]) rendered by gsplat on the surfels' device."""
    if surfels.device.type != "cuda":
        raise ValueError("the gsplat backend needs the surfels on a CUDA device")
    if not available():
        raise ValueError("the gsplat backend needs CUDA and the gsplat package (pip install flashmono[gpu])")
    from gsplat import rasterization_2dgs

    if len(surfels) == 0:
        zeros = torch.zeros(height, width, dtype=surfels.means.dtype, device=surfels.device)
        return torch.zeros(height, width, 7, dtype=zeros.dtype, device=zeros.device), zeros
    scales3 = torch.cat([surfels.scales, torch.ones_like(surfels.scales[:, :1])], dim=-1)  # 3rd scale unused
    # gsplat 1.5.3 takes non-SH colours per camera ([C, N, 3]); an [N, 3] tensor fails in its RGB+D concatenation
    colors, alphas, normals_world, *_ = rasterization_2dgs(
        means=surfels.means, quats=surfels.quats, scales=scales3, opacities=surfels.opacities,
        colors=surfels.colors[None], viewmats=viewmat[None], Ks=K[None], width=width, height=height,
        render_mode="RGB+D", packed=False,
    )
    normals_cam = normals_world[0] @ viewmat[:3, :3].T  # the caller rotates back to the world frame
    return torch.cat([colors[0], normals_cam], dim=-1), alphas[0, ..., 0]
