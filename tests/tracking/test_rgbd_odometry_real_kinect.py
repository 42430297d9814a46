"""RGB-D odometry on real Kinect v1 frames (tests/data/tum_fr1_rpy_mini: the first 10 frames of TUM fr1/rpy at
320x240, a fast rotation over a desk) against the benchmark's motion-capture ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.tracking.rgbd_odometry import RgbdOdometry

DATA = Path(__file__).parents[1] / "data" / "tum_fr1_rpy_mini"


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_odometry_follows_a_real_kinect_rotation() -> None:
    source = open_source(DATA, use_gt_depth=True)
    frames = list(source)
    odometry = RgbdOdometry()
    results = [odometry.track(f, source.intrinsics) for f in frames]
    assert len(frames) == 10 and all(f.depth is not None and f.gt_pose is not None for f in frames)
    assert all(r.tracked for r in results) and not any(r.events for r in results)
    est = np.stack([r.pose for r in results])
    gt = np.stack([f.gt_pose for f in frames])
    truth = np.linalg.inv(gt[0]) @ gt[-1]
    moved = np.linalg.inv(est[0]) @ est[-1]
    assert _angle_deg(truth[:3, :3]) > 15  # the clip does turn: 19.7 degrees in a third of a second
    # measured 1.5 degrees off over the 20 degrees (0.2-0.9 per frame) and 0.6 cm ATE
    assert _angle_deg(truth[:3, :3].T @ moved[:3, :3]) < 3.0
    assert absolute_trajectory_error(est, gt, "se3").rmse < 0.015
