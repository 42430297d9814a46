"""PSNR, SSIM, depth L1, FPS and the non-keyframe rendering evaluation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from worker.data.synthetic import make_sequence
from worker.eval import (
    Lpips,
    depth_l1,
    end_to_end_fps,
    evaluate_renders,
    gaussian_count,
    non_keyframe_indices,
    psnr,
    ssim,
)
from worker.mapping.surfels import Surfels


def test_psnr_of_a_constant_offset():
    gt = np.full((8, 10, 3), 0.5)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)  # mse = 0.01
    assert psnr(gt, gt) == math.inf


def test_psnr_uint8_is_scaled_and_float_is_clamped():
    gt = np.zeros((4, 4, 3), np.uint8)
    pred = np.full((4, 4, 3), 255, np.uint8)
    assert psnr(pred, gt) == pytest.approx(0.0)
    assert psnr(torch.full((4, 4, 3), 7.0), torch.zeros(4, 4, 3)) == pytest.approx(0.0)  # clamped to 1


def test_psnr_mask_restricts_pixels():
    gt = np.zeros((4, 4, 3))
    pred = gt.copy()
    pred[0] = 1.0
    mask = np.ones((4, 4), bool)
    mask[0] = False
    assert psnr(pred, gt, mask) == math.inf
    with pytest.raises(ValueError, match="no pixels"):
        psnr(pred, gt, np.zeros((4, 4), bool))


def test_shape_errors():
    with pytest.raises(ValueError, match="channels-last"):
        psnr(np.zeros((3, 4, 4)), np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="differ in shape"):
        ssim(np.zeros((4, 4, 3)), np.zeros((5, 4, 3)))


def reference_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """A direct loop implementation: 11x11 Gaussian (sigma 1.5) over a zero-padded image, per channel."""
    from scipy.ndimage import correlate

    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    values = []
    for c in range(3):
        a, b = x[..., c], y[..., c]

        def f(img):
            return correlate(img, w, mode="constant", cval=0.0)

        mu_a, mu_b = f(a), f(b)
        va, vb, cov = f(a * a) - mu_a ** 2, f(b * b) - mu_b ** 2, f(a * b) - mu_a * mu_b
        values.append(((2 * mu_a * mu_b + 1e-4) * (2 * cov + 9e-4))
                      / ((mu_a ** 2 + mu_b ** 2 + 1e-4) * (va + vb + 9e-4)))
    return float(np.mean(values))


def test_ssim_matches_a_direct_implementation():
    pytest.importorskip("scipy")
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (24, 31, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    assert ssim(y, x) == pytest.approx(reference_ssim(y, x), abs=1e-10)


def test_ssim_properties():
    rng = np.random.default_rng(2)
    x = rng.uniform(0, 1, (32, 32, 3))
    assert ssim(x, x) == pytest.approx(1.0)
    slightly = np.clip(x + rng.normal(0, 0.02, x.shape), 0, 1)
    very = np.clip(x + rng.normal(0, 0.2, x.shape), 0, 1)
    assert 1.0 > ssim(slightly, x) > ssim(very, x)
    assert ssim(slightly, x) == pytest.approx(ssim(x, slightly))


def test_depth_l1_median_scaling_removes_a_global_scale():
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.5, 4.0, (20, 30))
    gt[0, :] = 0.0  # invalid ground truth is ignored
    pred = gt / 3.0
    pred[1, :] = 0.0  # and so are pixels without a prediction
    result = depth_l1(pred, gt, "median")
    assert result.value == pytest.approx(0.0, abs=1e-12)
    assert result.scale == pytest.approx(3.0)
    assert result.valid_pixels == 18 * 30
    assert depth_l1(pred, gt, "lstsq").scale == pytest.approx(3.0)
    metric = depth_l1(np.where(gt > 0, gt + 0.1, 0), gt, "none")
    assert metric.value == pytest.approx(0.1) and metric.scale == 1.0


def test_depth_l1_errors():
    with pytest.raises(ValueError, match="scaling"):
        depth_l1(np.ones((2, 2)), np.ones((2, 2)), "mean")
    with pytest.raises(ValueError, match="no pixel"):
        depth_l1(np.zeros((2, 2)), np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"\[H, W\]"):
        depth_l1(np.ones((2, 3)), np.ones((2, 2)))


def test_fps_and_gaussian_count():
    assert end_to_end_fps(300, 25.0) == pytest.approx(12.0)
    with pytest.raises(ValueError):
        end_to_end_fps(10, 0.0)
    n = 7
    surfels = Surfels(means=torch.zeros(n, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                      scales=torch.ones(n, 2), opacities=torch.ones(n), colors=torch.zeros(n, 3),
                      keyframe_ids=torch.zeros(n, dtype=torch.int64))
    assert gaussian_count(surfels) == 7
    with pytest.raises(ValueError):
        gaussian_count(object())


def test_non_keyframe_indices():
    keys = [True, False, False, True, False, False, False]
    assert non_keyframe_indices(keys) == [1, 2, 4, 5, 6]
    assert non_keyframe_indices(keys, every=2) == [1, 4, 6]


def test_evaluate_renders_on_a_synthetic_scene():
    sequence = make_sequence(10_003, num_frames=6, width=48, height=36)
    frames = list(sequence)
    picked = [frames[i] for i in non_keyframe_indices([i % 3 == 0 for i in range(6)])]
    poses = [f.gt_pose for f in picked]
    no_lpips = Lpips(None, None, "LPIPS not available: test")

    perfect = evaluate_renders(sequence.scene.render, picked, poses, "none", no_lpips)
    assert perfect.num_frames == 4 and perfect.psnr == math.inf
    assert perfect.ssim == pytest.approx(1.0) and perfect.depth_l1 == pytest.approx(0.0)
    assert perfect.lpips is None and "not available" in perfect.lpips_note

    shifted = [p.copy() for p in poses]
    for p in shifted:
        p[:3, 3] += p[:3, 0] * 0.15  # 15 cm to the right
    worse = evaluate_renders(sequence.scene.render, picked, shifted, "none", no_lpips)
    assert worse.psnr < 30 and worse.ssim < 0.95 and worse.depth_l1 > 0.0


def test_hole_shares_measure_the_uncovered_area_and_its_largest_region():
    from worker.eval.metrics import hole_shares

    alpha = np.ones((100, 200))
    assert hole_shares(alpha) == (0.0, 0.0)
    alpha[10:20, 10:30] = 0.2  # a 10x20 hole ...
    alpha[50:52, 100:105] = 0.0  # ... and a 2x5 one
    alpha[80, 150] = 0.6  # covered enough: no hole
    uncovered, largest = hole_shares(alpha)
    assert uncovered == (200 + 10) / 20000 and largest == 200 / 20000
