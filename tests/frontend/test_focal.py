"""Focal length from a camera-frame pointmap (Weiszfeld), on a real ICL depth map."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from worker.frontend.focal import estimate_focal, intrinsics_from_focal
from worker.geometry import unproject_depth

ICL = Path(__file__).parent.parent / "data" / "icl_mini"


def _icl_points(focal: float) -> torch.Tensor:
    depth_mm = cv2.imread(str(ICL / "depth" / "00000.png"), cv2.IMREAD_UNCHANGED)
    depth = torch.from_numpy(depth_mm.astype(np.float32) / 1000.0)
    H, W = depth.shape
    K = torch.tensor([[focal, 0.0, W / 2], [0.0, focal, H / 2], [0.0, 0.0, 1.0]])
    return unproject_depth(depth, K)


def test_recovers_the_focal_of_an_exact_pointmap() -> None:
    points = _icl_points(262.5)
    assert estimate_focal(points) == pytest.approx(262.5, rel=1e-4)


def test_is_robust_to_gross_outliers_where_least_squares_is_not() -> None:
    points = _icl_points(262.5).clone()
    g = torch.Generator().manual_seed(0)
    mask = torch.rand(points.shape[:2], generator=g) < 0.15
    points[mask] = points[mask] * torch.tensor([3.0, 3.0, 1.0])  # rays 3x too wide: a 3x shorter focal
    robust = estimate_focal(points, iterations=10)
    least_squares = estimate_focal(points, iterations=0)
    assert robust == pytest.approx(262.5, rel=0.02)
    assert abs(least_squares - 262.5) > 3 * abs(robust - 262.5)


def test_confidence_down_weights_bad_pixels() -> None:
    points = _icl_points(300.0).clone()
    points[:, :160] *= torch.tensor([2.0, 2.0, 1.0])
    conf = torch.ones(points.shape[:2])
    conf[:, :160] = 1e-6
    assert estimate_focal(points, conf) == pytest.approx(300.0, rel=1e-3)


def test_intrinsics_from_focal_centres_the_principal_point() -> None:
    K = intrinsics_from_focal(250.0, 224, 160)
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (250.0, 250.0, 112.0, 80.0, 224, 160)


def test_bad_inputs_are_rejected() -> None:
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        estimate_focal(torch.zeros(4, 4))
    with pytest.raises(ValueError, match="conf"):
        estimate_focal(torch.ones(4, 4, 3), conf=torch.ones(3, 3))
    behind = torch.ones(4, 4, 3)
    behind[..., 2] = -1
    with pytest.raises(ValueError, match="in front of the camera"):
        estimate_focal(behind)
