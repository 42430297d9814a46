"""Surfel grids from a model prediction: the confidence gate and ray-aligned means."""

from __future__ import annotations

import pytest
import torch

from worker.geometry import pixel_grid, unproject_depth
from worker.pipeline.surfel_init import confidence_mask, grid_from_prediction

H, W = 12, 16
K = torch.tensor([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]])


def prediction(seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    z = 1.0 + torch.rand(H, W, generator=gen)
    rays = unproject_depth(torch.ones(H, W), K)
    # directions off their pixels' rays by up to ~20 % of the field of view, as an undertrained model's are
    points = (rays + 0.1 * torch.randn(H, W, 3, generator=gen) * torch.tensor([1.0, 1.0, 0.0])) * z[..., None]
    return {"points": points, "conf": 1.0 + torch.rand(H, W, generator=gen),
            "quats": torch.tensor([1.0, 0, 0, 0]).expand(H, W, 4), "scales": torch.full((H, W, 2), 0.01),
            "opacities": torch.full((H, W), 0.9), "colors": torch.rand(H, W, 3, generator=gen)}


def test_confidence_gate_keeps_a_floor_fraction_only_when_too_few_pass() -> None:
    conf = torch.linspace(1.0, 2.0, H * W).reshape(H, W)
    assert confidence_mask(conf, 1.5).float().mean() == pytest.approx(0.5, abs=0.01)
    assert not confidence_mask(conf, 2.5).any()
    kept = confidence_mask(conf, 2.5, min_kept_fraction=0.3)
    assert kept.float().mean() == pytest.approx(0.3, abs=0.01)
    assert conf[kept].min() >= conf[~kept].max()  # the most confident ones
    assert torch.equal(confidence_mask(conf, 1.5, min_kept_fraction=0.3), confidence_mask(conf, 1.5))


def test_ray_aligned_means_sit_on_their_pixel_rays_at_the_predicted_depth() -> None:
    p = prediction()
    free = grid_from_prediction(p["points"], p["conf"], p["quats"], p["scales"], p["opacities"], p["colors"], 1.0)
    aligned = grid_from_prediction(p["points"], p["conf"], p["quats"], p["scales"], p["opacities"], p["colors"], 1.0,
                                   K=K, ray_aligned=True)
    assert torch.equal(free["means"], p["points"])
    assert torch.allclose(aligned["means"][..., 2], p["points"][..., 2])
    projected = aligned["means"] @ K.T
    pixels = projected[..., :2] / projected[..., 2:]
    assert torch.allclose(pixels, pixel_grid(W, H), atol=1e-4)
    assert not torch.allclose(free["means"], aligned["means"], atol=1e-3)
    behind = p["points"].clone()
    behind[0, 0, 2] = -1.0
    g = grid_from_prediction(behind, p["conf"], p["quats"], p["scales"], p["opacities"], p["colors"], 1.0, K=K,
                             ray_aligned=True)
    assert not g["valid"][0, 0] and g["valid"].sum() == H * W - 1
    with pytest.raises(ValueError, match="K is needed"):
        grid_from_prediction(p["points"], p["conf"], p["quats"], p["scales"], p["opacities"], p["colors"], 1.0,
                             ray_aligned=True)
