"""Monocular visual odometry coming back: the ICL clip played forward and back offers the engine few keyframes on the
way back (an old engine keyframe near the pose sees the view), while tracking stays as accurate."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.data.sources.pingpong import sweep_order
from worker.eval import absolute_trajectory_error
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def sequence():
    frames = list(open_source(DATA, use_gt_depth=False, use_gt_poses=False))
    order = sweep_order(len(frames), 2)
    return [replace(frames[p], index=i, timestamp=i / 30) for i, p in enumerate(order)], len(frames)


def run(frames, vo: VisualOdometry):
    """Every keyframe VO offers becomes an engine keyframe (as in the engine: VO's hint decides)."""
    poses, keyframes = [], []
    for frame in frames:
        result = vo.track(frame, frame.intrinsics)
        if result.keyframe_hint:
            keyframes.append(frame.index)
            vo.keyframe_added(frame, result.pose)
        poses.append(result.pose)
    return np.stack(poses), keyframes


def test_the_way_back_offers_few_keyframes(sequence) -> None:
    frames, length = sequence
    vo = VisualOdometry()
    poses, keyframes = run(frames, vo)
    first = sum(k < length for k in keyframes)
    later = len(keyframes) - first
    _, without_reuse = run(frames, VisualOdometry(VisualOdometryConfig(reuse_keyframes=0)))
    assert len(without_reuse) - first > 0.6 * first  # the way back made its own keyframes
    assert later < 0.5 * (len(without_reuse) - first), (first, later, len(without_reuse))
    tracked = np.array([np.all(np.isfinite(p)) for p in poses])
    gt = np.stack([f.gt_pose for f in frames])
    assert absolute_trajectory_error(poses[tracked][40:], gt[tracked][40:], "sim3").rmse < 0.05
    restored = VisualOdometry()
    restored.load_state_dict(unpack(pack(vo.state_dict())))
    assert [k for k, _ in restored.engine_keyframes] == [k for k, _ in vo.engine_keyframes]
