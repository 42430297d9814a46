"""GPU parity: gsplat.rasterization_2dgs (backend "gsplat") against the compiled CPU path. Needs CUDA + gsplat."""

from __future__ import annotations

import pytest
import torch
from test_rasterize import look_from, random_scene, random_weights

from worker.mapping import raster_gsplat
from worker.mapping.surfels import Surfels

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not raster_gsplat.available(), reason="needs CUDA and the gsplat package"),
]

W, H = 64, 48
ATTRIBUTES = ("means", "quats", "scales", "opacities", "colors")


def render(scene: Surfels, viewmat: torch.Tensor, backend: str, device: str, weights):
    from worker.mapping import rasterize

    leaves = [getattr(scene, k).detach().to(device).clone().requires_grad_(True) for k in ATTRIBUTES]
    V = viewmat.to(device).clone().requires_grad_(True)
    K = torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]], device=device)
    out = rasterize(Surfels(*leaves, keyframe_ids=scene.keyframe_ids.to(device)), V, K, W, H,
                    background=torch.tensor([0.2, 0.4, 0.6], device=device), backend=backend)
    sum((w.to(device) * o).sum() for w, o in zip(weights, out)).backward()
    return [o.detach().cpu() for o in out], [t.grad.cpu() for t in (*leaves, V)]


def test_gsplat_matches_the_cpu_path():
    scene = random_scene(300, seed=11, dtype=torch.float32, scale_range=(0.02, 0.2), opacity_range=(0.2, 0.99),
                         extent=(1.2, 0.9))
    V = look_from(-0.08, t=(0.1, 0.05, -0.2), dtype=torch.float32)
    weights = random_weights(W, H, seed=2, dtype=torch.float32)
    gpu_out, gpu_grads = render(scene, V, "gsplat", "cuda", weights)
    cpu_out, cpu_grads = render(scene, V, "cpu", "cpu", weights)
    for name, a, b in zip(("rgb", "depth", "alpha", "normals"), gpu_out, cpu_out):
        assert (a - b).abs().max() < 1e-4, name
    gpu_grads[-1], cpu_grads[-1] = gpu_grads[-1][:3], cpu_grads[-1][:3]
    # viewmat's bottom row is the constant [0, 0, 0, 1]: gsplat returns a (meaningless) gradient for it, we return 0
    for name, a, b in zip((*ATTRIBUTES, "viewmat"), gpu_grads, cpu_grads):
        scale = max(1.0, b.abs().max().item())
        assert (a - b).abs().max() < 1e-3 * scale, f"d/d{name}"
