"""RGB-D odometry on real Kinect v1 frames (tests/data/tum_fr1_rpy_mini: the first 10 frames of TUM fr1/rpy at
320x240, a fast rotation over a desk) against the benchmark's motion-capture ground truth."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.tracking.rgbd_config import RgbdOdometryConfig
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


def _motion_blurred(image: np.ndarray, length: int = 25) -> np.ndarray:
    """A horizontal motion blur of `length` pixels (a fast pan during the exposure)."""
    kernel = np.zeros((length, length), np.float32)
    kernel[length // 2, :] = 1.0 / length
    return cv2.filter2D(image, -1, kernel)


def test_a_motion_blurred_frame_is_tracked_on_its_depth_and_a_wrong_one_is_not() -> None:
    source = open_source(DATA, use_gt_depth=True)
    frames = list(source)
    blurred = [replace(f, image=_motion_blurred(f.image)) if n in (5, 6) else f for n, f in enumerate(frames)]
    odometry = RgbdOdometry()
    results = [odometry.track(f, source.intrinsics) for f in blurred]
    assert all(r.tracked for r in results), [r.events for r in results]
    gt = np.stack([f.gt_pose for f in frames])
    assert absolute_trajectory_error(np.stack([r.pose for r in results]), gt, "se3").rmse < 0.02
    # The same blur without the geometric allowance is a loss: the intensities alone fit too poorly.
    strict = RgbdOdometry(RgbdOdometryConfig(blurred_photometric_residual=0.12))
    assert not all(strict.track(f, source.intrinsics).tracked for f in blurred)
    # A frame from elsewhere (colour and depth of a view 1.3 m away in another sequence: ICL's living room) is
    # not held by its depth: lost, not a pose.
    icl = open_source(Path(__file__).parents[1] / "data" / "icl_mini", use_gt_depth=True, resize=(320, 240))
    stranger = next(iter(icl))
    wrong = odometry.track(replace(stranger, index=10, intrinsics=None), source.intrinsics)
    assert not wrong.tracked
