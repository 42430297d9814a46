"""Evaluation of a frontend against trajectory baselines (bench/training.py's building blocks)."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from worker.frontend import build_model
from worker.frontend.configs import get_config
from worker.geometry import se3_exp
from worker.training.evaluate import (
    constant_velocity_poses,
    depth_abs_rel,
    evaluate_baselines,
    evaluate_model,
    held_out_synthetic,
    identity_poses,
    next_view_psnr,
    trajectory_ate,
)

MICRO = replace(get_config("tiny"), name="micro", enc_dim=48, enc_depth=2, enc_heads=2, dec_dim=32, dec_heads=2,
                state_dec_heads=2, state_size=16, memory_size=4, memory_heads=2, dpt_layer_dims=(8, 8, 16, 16),
                dpt_feature_dim=16, dpt_last_dim=8, gs_adapter_hidden=32, image_long_side=64)


def test_baselines_on_a_constant_twist_path():
    step = se3_exp(torch.tensor([0.02, 0.0, 0.1, 0.0, 0.05, 0.0], dtype=torch.float64)).numpy()
    gt = [np.eye(4)]
    for _ in range(11):
        gt.append(gt[-1] @ step)
    gt = np.stack(gt)
    assert trajectory_ate(constant_velocity_poses(gt), gt) < 1e-9
    still = identity_poses(gt)
    assert np.allclose(still, gt[0])
    spread = np.sqrt(((gt[:, :3, 3] - gt[:, :3, 3].mean(0)) ** 2).sum(1).mean())
    assert trajectory_ate(still, gt) == pytest.approx(spread) and spread > 0.1
    noisy = gt.copy()
    noisy[:, :3, 3] += np.random.default_rng(0).normal(0, 0.01, (12, 3))
    assert 0.002 < trajectory_ate(noisy, gt) < 0.02


def test_depth_abs_rel_is_scale_free_and_counts_valid_pixels_only():
    gt = np.random.default_rng(1).uniform(1, 4, (6, 8))
    assert depth_abs_rel(gt * 3.0, gt) == pytest.approx(0.0, abs=1e-12)
    off = gt.copy()
    off[0] *= 1.5
    assert 0.01 < depth_abs_rel(off, gt) < 0.2
    gt_holes = gt.copy()
    gt_holes[0] = 0
    assert depth_abs_rel(off, gt_holes) == pytest.approx(0.0, abs=1e-12)
    assert math.isnan(depth_abs_rel(-gt, gt))


def test_held_out_synthetic_and_model_evaluation():
    with pytest.raises(ValueError, match="held out"):
        held_out_synthetic(2, frames=3, width=64, height=48, first_seed=9_999)
    seqs = held_out_synthetic(1, frames=5, width=64, height=48)
    seq = seqs[0]
    assert seq.name == "synthetic-10000" and seq.images.shape == (5, 48, 64, 3) and seq.depths.min() > 0
    identity, velocity = evaluate_baselines(seq)
    assert identity.method == "identity" and velocity.ate < identity.ate
    torch.manual_seed(0)
    scores = evaluate_model(build_model(MICRO), seq, submap_length=3)
    assert scores.method == "model" and math.isfinite(scores.ate) and scores.ate >= 0
    assert math.isfinite(scores.psnr) and 0 < scores.psnr < 60
    assert math.isfinite(scores.psnr_next) and 0 < scores.psnr_next < 60
    assert math.isfinite(scores.ate_pointmap) and scores.ate_pointmap >= 0


def test_next_view_psnr_rewards_surfels_that_reproject_correctly():
    from worker.frontend.tracker import CameraSurfels
    from worker.geometry import Intrinsics, unproject_depth

    seq = held_out_synthetic(1, frames=2, width=64, height=48)[0]
    H, W = seq.images.shape[1:3]
    K = torch.as_tensor(seq.K, dtype=torch.float32)
    points = unproject_depth(torch.as_tensor(seq.depths[0]), K)
    footprint = points[..., 2:3] / Intrinsics.from_matrix(K, W, H).fx

    def surfels(scale: float) -> CameraSurfels:
        quats = torch.zeros(H, W, 4)
        quats[..., 0] = 1.0
        return CameraSurfels(points * scale, torch.ones(H, W), torch.full((H, W), 0.95), quats,
                             footprint.expand(H, W, 2) * scale, torch.as_tensor(seq.images[0]).float() / 255)

    to_next = np.linalg.inv(seq.c2w[1]) @ seq.c2w[0]
    exact = next_view_psnr(surfels(1.0), seq.depths[0], to_next, seq.images[1], seq.K)
    assert exact > 18
    assert next_view_psnr(surfels(0.3), seq.depths[0], to_next, seq.images[1], seq.K) == pytest.approx(exact, abs=0.05)
    wrong = to_next.copy()
    wrong[:3, 3] += np.array([0.3, 0.0, 0.0])
    assert next_view_psnr(surfels(1.0), seq.depths[0], wrong, seq.images[1], seq.K) < exact - 2
    assert math.isnan(next_view_psnr(surfels(1.0), np.zeros((H, W)), to_next, seq.images[1], seq.K))
