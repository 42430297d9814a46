"""RGB-D odometry reuses keyframes when the camera comes back: the ICL clip played forward, back and forward again
asks for few keyframes after the first sweep, tracks against the old ones without a jump, and stays accurate."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.data.sources.pingpong import sweep_order
from worker.eval import absolute_trajectory_error
from worker.pipeline.keyframes import MotionKeyframeSelector
from worker.tracking.rgbd_config import RgbdOdometryConfig
from worker.tracking.rgbd_odometry import RgbdOdometry

DATA = Path(__file__).parents[1] / "data" / "icl_mini"
SWEEPS = 2


@pytest.fixture(scope="module")
def sequence():
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=False)
    frames = list(src)
    order = sweep_order(len(frames), SWEEPS)
    return [replace(frames[p], index=i, timestamp=i / 30) for i, p in enumerate(order)], src.intrinsics, len(frames)


def run(frames, intr, odometry: RgbdOdometry):
    """The engine's keyframe rule (the rgbd preset's selector, vetoed or forced by the source's hint)."""
    selector = MotionKeyframeSelector(6, 0.2, 15.0)
    poses, keyframes = [], []
    for frame in frames:
        result = odometry.track(frame, intr)
        if not keyframes or (result.keyframe_hint is not False
                             and selector.is_keyframe(result.pose, force=bool(result.keyframe_hint))):
            keyframes.append(frame.index)
            odometry.keyframe_added(frame, result.pose)
        poses.append(result.pose)
    return np.stack(poses), keyframes


def test_coming_back_tracks_against_old_keyframes_instead_of_making_new_ones(sequence) -> None:
    frames, intr, length = sequence
    odometry = RgbdOdometry()
    poses, keyframes = run(frames, intr, odometry)
    first = sum(k < length for k in keyframes)
    later = len(keyframes) - first
    _, without_reuse = run(frames, intr, RgbdOdometry(RgbdOdometryConfig(reuse_keyframes=0)))
    assert len(without_reuse) > 1.6 * first  # the way back made its own keyframes
    assert later < 0.4 * first, (first, later, len(without_reuse))
    gt = np.stack([f.gt_pose for f in frames])
    assert absolute_trajectory_error(poses, gt, "se3").rmse < 0.03
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    true_steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    assert np.all(steps < true_steps + 0.03)  # no jump when the reference switches
    # the places to come back to are part of the state
    restored = RgbdOdometry()
    restored.load_state_dict(unpack(pack(odometry.state_dict())))
    assert [p.index for p in restored.places] == [p.index for p in odometry.places] and len(odometry.places) > 3
    assert np.allclose(restored.places[-1].pose, odometry.places[-1].pose)


def test_frames_tracked_against_an_old_keyframe_carry_it_as_their_anchor(sequence) -> None:
    frames, intr, length = sequence
    odometry = RgbdOdometry()
    selector = MotionKeyframeSelector(6, 0.2, 15.0)
    keyframes, measured = [], []
    for frame in frames:
        result = odometry.track(frame, intr)
        if result.anchor is not None:
            keyframe, relative = result.anchor
            assert keyframe in keyframes and keyframe < frame.index
            true = np.linalg.inv(frames[keyframe].gt_pose) @ frame.gt_pose
            measured.append(np.linalg.norm(relative[:3, 3] - true[:3, 3]))
        if not keyframes or (result.keyframe_hint is not False
                             and selector.is_keyframe(result.pose, force=bool(result.keyframe_hint))):
            keyframes.append(frame.index)
            odometry.keyframe_added(frame, result.pose)
    assert len(measured) > 0.3 * (len(frames) - length)  # much of the way back is measured against the first sweep
    assert np.mean(measured) < 0.01 and np.max(measured) < 0.03  # the true motion from the old keyframe
