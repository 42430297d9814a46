"""The pose source is chosen once per session from the config and the first frame, and the one frame path serves
them all: RGB-D frames without poses are tracked by RGB-D odometry (keyframes, map, loop closer unchanged), events
reach the FrameResult, bad input never yields a NaN pose, and a snapshot continues the session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.data.frame import Frame
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem
from worker.tracking.sources import choose_tracking

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def rgbd_frames():
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=False, max_frames=24)
    return list(src), src.intrinsics


def _config(mapping: bool = True) -> SlamConfig:
    return SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": mapping, "refine_iterations": 1,
                                                              "final_refine_passes": 0})


def test_auto_choice_follows_what_the_frames_carry() -> None:
    frame = Frame(0, 0.0, np.zeros((8, 8, 3), np.uint8))
    assert choose_tracking("auto", frame, uses_pose=True, uses_depth=True, custom_model=False) == "device"
    assert choose_tracking("auto", frame, uses_pose=False, uses_depth=True, custom_model=False) == "rgbd_odometry"
    assert choose_tracking("auto", frame, uses_pose=False, uses_depth=False, custom_model=False) == "visual_odometry"
    assert choose_tracking("auto", frame, uses_pose=False, uses_depth=True, custom_model=True) == "model"
    with pytest.raises(ValueError, match="needs depth"):
        choose_tracking("rgbd_odometry", frame, uses_pose=False, uses_depth=False, custom_model=False)
    with pytest.raises(ValueError, match="needs poses"):
        choose_tracking("device", frame, uses_pose=False, uses_depth=True, custom_model=False)


def test_rgbd_frames_without_poses_are_tracked_and_mapped(rgbd_frames) -> None:
    frames, intr = rgbd_frames
    system = SlamSystem(_config(), intr)
    results = [system.push(f) for f in frames]
    system.finish()
    assert system.mode == "rgbd_odometry" and system.tracker is None  # no model: depth surfels, geometric poses
    poses = np.stack([p for _, _, p in system.trajectory()])
    gt = np.stack([f.gt_pose for f in frames])
    assert absolute_trajectory_error(poses, gt, "se3").rmse < 0.03
    assert sum(r.is_keyframe for r in results) >= 3 and system.num_gaussians > 1000
    rgb, _ = system.render_view(poses[5], intr.matrix(), intr.width, intr.height)
    assert float(np.abs(rgb.astype(np.float32) - frames[5].image).mean()) < 20  # the map explains the view
    assert not results[-1].is_keyframe and system.last_frame_mapped == frames[-1].index  # finish maps the last view
    rgb, _ = system.render_view(poses[-1], intr.matrix(), intr.width, intr.height)
    assert float(np.abs(rgb.astype(np.float32) - frames[-1].image).mean()) < 20
    system.close()


def test_lost_frames_pass_their_event_and_keep_the_pose(rgbd_frames) -> None:
    frames, intr = rgbd_frames
    system = SlamSystem(_config(mapping=False), intr)
    for f in frames[:4]:
        before = system.push(f)
    black = Frame(frames[4].index, frames[4].timestamp, np.zeros_like(frames[4].image), intr,
                  np.zeros_like(frames[4].depth))
    lost = system.push(black)
    assert [e.TYPE for e in lost.events] == ["tracking_lost"] and not lost.is_keyframe
    np.testing.assert_allclose(lost.pose, before.pose)
    back = system.push(frames[5])
    assert [e.TYPE for e in back.events] == ["relocalized"] and np.all(np.isfinite(back.pose))


def test_snapshot_restores_the_odometry(rgbd_frames) -> None:
    frames, intr = rgbd_frames
    config = _config(mapping=False)
    straight = SlamSystem(config, intr)
    expected = [straight.push(f).pose for f in frames[:10]]
    first = SlamSystem(config, intr)
    for f in frames[:6]:
        first.push(f)
    restored = SlamSystem.restore(first.snapshot())
    assert restored.tracking == "rgbd_odometry"
    got = [restored.push(f).pose for f in frames[6:10]]
    for a, b in zip(got, expected[6:]):
        np.testing.assert_allclose(a, b, atol=3e-3)
