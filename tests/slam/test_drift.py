"""The injected odometry drift: per-frame errors compound along the chain, as a real odometry's do."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from worker.geometry import make_sim3, relative_transform, so3_exp, so3_log
from worker.pipeline.drift import PoseDrift


def straight_path(n: int = 40) -> np.ndarray:
    """Camera moving 5 cm per frame along its own z while turning 1 degree per frame about y."""
    poses = []
    for k in range(n):
        R = so3_exp(torch.tensor([0.0, math.radians(k), 0.0], dtype=torch.float64))
        poses.append(make_sim3(R, torch.tensor([0.0, 0.0, 0.05 * k], dtype=torch.float64)).numpy())
    return np.stack(poses)


def test_no_drift_keeps_the_poses() -> None:
    poses = straight_path()
    np.testing.assert_allclose(PoseDrift().apply_to_trajectory(poses), poses, atol=1e-12)


def test_each_frame_motion_carries_the_bias() -> None:
    poses = straight_path()
    drifted = PoseDrift(rotation_bias_deg=0.1, translation_bias=0.002).apply_to_trajectory(poses)
    np.testing.assert_allclose(drifted[0], poses[0])
    for k in range(1, len(poses)):
        true_motion = relative_transform(torch.from_numpy(poses[k - 1]), torch.from_numpy(poses[k]))
        measured = relative_transform(torch.from_numpy(drifted[k - 1]), torch.from_numpy(drifted[k]))
        error = torch.linalg.inv(true_motion) @ measured
        assert math.degrees(float(so3_log(error[:3, :3]).norm())) == pytest.approx(0.1, rel=1e-6)
        assert float(error[:3, 3].norm()) == pytest.approx(0.002, rel=1e-6)


def test_errors_compound_faster_than_linearly() -> None:
    poses = straight_path(60)
    drifted = PoseDrift(rotation_bias_deg=0.05).apply_to_trajectory(poses)
    err = np.linalg.norm(drifted[:, :3, 3] - poses[:, :3, 3], axis=1)
    assert err[0] == 0 and err[20] > 0
    assert err[59] > 2.5 * err[29]  # a heading error turns every later step: quadratic growth


def test_noise_is_seeded() -> None:
    poses = straight_path()
    a = PoseDrift(0.0, 0.0, 0.05, 0.001, seed=3).apply_to_trajectory(poses)
    b = PoseDrift(0.0, 0.0, 0.05, 0.001, seed=3).apply_to_trajectory(poses)
    c = PoseDrift(0.0, 0.0, 0.05, 0.001, seed=4).apply_to_trajectory(poses)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-4


def test_bad_drift_is_rejected() -> None:
    with pytest.raises(ValueError, match="rotation_bias_deg"):
        PoseDrift(rotation_bias_deg=-1.0)
    with pytest.raises(ValueError, match="translation_noise"):
        PoseDrift(translation_noise=float("nan"))
