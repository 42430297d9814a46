"""Colour skip of small models: Gaussian colour = sigmoid(logit(pixel) + raw), and the weight surgery that turns
it on for trained weights (worker.training.color_skip)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from frontend_test_config import TEST_CONFIG, single_torch_thread  # noqa: F401

from worker.frontend import FeedForwardModel, build_model
from worker.frontend.configs import get_config
from worker.frontend.heads import gaussian_attributes
from worker.training.color_skip import with_color_skip


def _image() -> torch.Tensor:
    return torch.rand(1, 3, 48, 64, generator=torch.Generator().manual_seed(1))


def test_small_configs_have_the_skip_and_the_paper_config_does_not():
    assert get_config("tiny").color_skip and get_config("small").color_skip
    assert not get_config("paper").color_skip and not get_config("base").color_skip
    assert get_config("tiny").from_dict(get_config("tiny").to_dict()).color_skip
    older = get_config("tiny").to_dict()
    del older["color_skip"]  # a checkpoint written before the flag existed keeps plain sigmoid colours
    assert not get_config("tiny").from_dict(older).color_skip


def test_gaussian_colour_is_a_residual_on_the_pixel_colour():
    raw = torch.zeros(1, 4, 5, 10)
    points = torch.ones(1, 4, 5, 3)
    pixels = torch.rand(1, 4, 5, 3)
    pixels[0, 0, 0] = torch.tensor([0.0, 1.0, 0.5])  # saturated pixels stay finite
    colors = gaussian_attributes(raw, points, pixels)[0]
    assert torch.allclose(colors, pixels, atol=1.1e-3)
    raw[..., 0] = 2.0
    brighter = gaussian_attributes(raw, points, pixels)[0]
    assert (brighter[..., 0] >= colors[..., 0]).all() and torch.allclose(brighter[..., 1:], colors[..., 1:])
    assert torch.allclose(gaussian_attributes(raw, points)[0], torch.sigmoid(raw[..., :3]))


def test_surgery_starts_every_surfel_at_its_pixel_colour_and_changes_nothing_else():
    torch.manual_seed(0)
    plain = FeedForwardModel(TEST_CONFIG).eval()
    skip = with_color_skip(plain).eval()
    assert skip.config.color_skip and not plain.config.color_skip
    image = _image()
    with torch.no_grad():
        a = plain.step(image, plain.init_state())
        b = skip.step(image, skip.init_state())
    pixels = image[0].permute(1, 2, 0)
    assert torch.allclose(b.colors[0], pixels, atol=1.1e-3)
    assert (a.colors[0] - pixels).abs().mean() > 0.1
    for name in ("pose_c2w", "points_cam", "points_world", "opacity", "scales", "quats", "conf"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_colour_skip_model_starts_at_the_pixels_needs_the_image_and_trains_the_residual():
    torch.manual_seed(0)
    model = build_model(replace(TEST_CONFIG, color_skip=True)).train()
    image = _image()
    out = model.step(image, model.init_state())
    assert torch.allclose(out.colors[0], image[0].permute(1, 2, 0), atol=1.1e-3)  # a fresh model: residual 0
    out.colors.mean().backward()
    assert model.downstream_head.dpt_gs.head[-1].weight.grad[:3].abs().sum() > 0
    features = [torch.zeros(1, 12, 64)] + [torch.zeros(1, 12, 64)] * 3
    with pytest.raises(ValueError, match="needs the input image"):
        model.downstream_head(features, torch.zeros(1, 64), torch.zeros(1, 12, 2, dtype=torch.long), (3, 4))
