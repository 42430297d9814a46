"""The synthetic street (worker.data.street): forward driving motion with a large depth range, rendered exactly;
RGB-D odometry tracks it to a small fraction of the path."""

from __future__ import annotations

import numpy as np
import pytest

from worker.data import DatasetError, open_source
from worker.eval import absolute_trajectory_error
from worker.tracking.rgbd_odometry import RgbdOdometry


@pytest.fixture(scope="module")
def street():
    src = open_source("synthetic://seed=2?frames=24&scene=street&fps=10&width=160&height=120", use_gt_depth=True)
    return list(src), src.intrinsics


def test_the_street_is_a_forward_drive_with_far_depth(street) -> None:
    frames, _ = street
    gt = np.stack([f.gt_pose for f in frames])
    steps = np.diff(gt[:, :3, 3], axis=0)
    forward = np.array([f.gt_pose[:3, 2] for f in frames[1:]])
    assert np.all(np.linalg.norm(steps, axis=1) > 0.9)  # about a metre per frame
    assert np.all((steps * forward).sum(1) > 0.9 * np.linalg.norm(steps, axis=1))  # along the view
    depth = frames[5].depth
    assert depth.min() < 6 and np.percentile(depth, 99) > 60  # near road, far street end


def test_rgbd_odometry_tracks_the_drive(street) -> None:
    frames, intr = street
    odometry = RgbdOdometry()
    poses = [odometry.track(f, intr).pose for f in frames]
    gt = np.stack([f.gt_pose for f in frames])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    assert absolute_trajectory_error(np.stack(poses), gt, "se3").rmse < 0.005 * path


def test_bad_scene_names_and_overlong_drives_are_refused() -> None:
    with pytest.raises(DatasetError, match="unknown synthetic scene"):
        open_source("synthetic://seed=1?scene=forest")
    with pytest.raises(DatasetError, match="at most"):
        open_source("synthetic://seed=1?scene=street&frames=5000")
