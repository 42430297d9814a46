"""Seeded visual odometry's final bundle adjustment laid on the device's poses (SeededTracking.keyframe_corrections):
real TUM fr1/xyz frames 40-87 (tests/data/tum_fr1_xyz_mini, CC BY 4.0) played forward and back, with the motion
capture sent as the device's poses, as it is and drifting."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from worker.data import open_source
from worker.data.sources.pingpong import sweep_order
from worker.eval import absolute_trajectory_error
from worker.tracking.seeded import SeededTracking, _fit_robustly
from worker.tracking.seeded_config import DevicePoseConfig
from worker.tracking.visual_odometry import VisualOdometry

DATA = Path(__file__).parents[1] / "data" / "tum_fr1_xyz_mini"


def _drifting(poses: list[np.ndarray], per_frame_deg: float, per_frame_m: float) -> list[np.ndarray]:
    """The poses in a world that turns (about the vertical) and slides a little more each frame."""
    out = []
    for i, pose in enumerate(poses):
        angle = np.radians(per_frame_deg * i)
        drift = np.eye(4)
        drift[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        drift[0, 3] = per_frame_m * i
        out.append(drift @ pose)
    return out


def _seeded_over(sweeps: int, drift: tuple[float, float] = (0.0, 0.0)):
    source = open_source(str(DATA))
    recorded = list(source)
    frames = [replace(recorded[p], index=i, timestamp=i / 30) for i, p in enumerate(sweep_order(len(recorded), sweeps))]
    truth = {f.index: f.gt_pose for f in frames}
    devices = _drifting([f.gt_pose for f in frames], *drift)
    seeded = SeededTracking(VisualOdometry(), DevicePoseConfig(), monocular=True)
    for frame, device in zip(frames, devices):
        seeded.track(replace(frame, pose=device), source.intrinsics)
    return seeded, truth


def _ate(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray], align: str) -> float:
    keys = sorted(poses)
    return absolute_trajectory_error(np.stack([poses[k] for k in keys]), np.stack([truth[k] for k in keys]),
                                     align).rmse


def test_the_adjusted_keyframes_land_on_the_device_poses_nearer_than_the_poses_handed_out() -> None:
    seeded, truth = _seeded_over(3)
    moves = seeded.keyframe_corrections()
    assert seeded.final_adjustment is not None and seeded.final_adjustment.poses
    assert len(moves) >= 10 and set(moves) <= set(seeded.keyframe_marks)
    given = {k: seeded.keyframe_marks[k][0] for k in moves}
    placed = {k: moves[k] @ given[k] for k in moves}
    for pose in placed.values():  # a rotation scaled by the keyframe's local scale (worker.tracking.keyframe_scale)
        scale = np.cbrt(np.linalg.det(pose[:3, :3]))
        assert 0.8 < scale < 1.25 and np.allclose(pose[:3, :3] @ pose[:3, :3].T, scale**2 * np.eye(3), atol=1e-9)
    # no alignment: the device's world and units are the session's
    assert _ate(placed, truth, "none") < 0.9 * _ate(given, truth, "none")
    assert _ate(placed, truth, "none") < 0.02
    assert set(seeded.final_adjustment.poses) == set(moves)  # the stats count the keyframes placed
    low, median, high = seeded.final_adjustment.local_scales  # ... and the spread of their scales
    assert 0.8 < low <= median <= high < 1.25
    seeded.keyframe_marks.clear()  # no keyframe with a device pose: the placing gives up, and says so
    assert seeded.keyframe_corrections() == {} and not seeded.final_adjustment.poses
    assert seeded.odometry.final_adjustment.poses


def test_a_drifting_device_places_the_adjusted_shape_without_bending_it() -> None:
    seeded, truth = _seeded_over(3, drift=(0.03, 0.0003))
    moves = seeded.keyframe_corrections()
    placed = {k: moves[k] @ seeded.keyframe_marks[k][0] for k in moves}
    given = {k: seeded.keyframe_marks[k][0] for k in moves}
    assert _ate(placed, truth, "sim3") < _ate(given, truth, "sim3")


def test_one_pass_is_left_alone_and_rgbd_has_nothing_to_adjust() -> None:
    seeded, _ = _seeded_over(1)
    assert seeded.keyframe_corrections() == {}
    rgbd = SeededTracking(VisualOdometry(), DevicePoseConfig(), monocular=False)
    assert rgbd.keyframe_corrections() == {}


def test_the_fit_leaves_out_a_device_pose_that_jumped() -> None:
    rng = np.random.default_rng(3)
    similarity = np.eye(4)
    angle = 0.4
    similarity[:3, :3] = 1.7 * np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                                         [0, 0, 1]])
    similarity[:3, 3] = [0.3, -1.0, 2.0]
    own = []
    for _ in range(12):
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(size=3)
        own.append(pose)
    device = []
    for pose in own:
        placed = similarity @ pose
        placed[:3, :3] /= 1.7
        device.append(placed)
    device[5] = device[5].copy()
    device[5][:3, 3] += [2.0, 0.0, 0.0]
    assert np.allclose(_fit_robustly(own, device), similarity, atol=1e-9)
