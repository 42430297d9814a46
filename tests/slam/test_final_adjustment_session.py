"""An RGB-only session's finish runs visual odometry's final bundle adjustment: the trajectory's keyframes and frames
move to it and one `poses_refined` event says so; a failing adjustment leaves the poses as they were. Real ICL-NUIM
frames (tests/data/icl_mini, CC BY 3.0) played forward and back, so that the camera comes back."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.data.sources.pingpong import sweep_order
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def coming_back():
    source = open_source(str(DATA), use_gt_depth=False, use_gt_poses=False)
    recorded = list(source)
    frames = [replace(recorded[p], index=i, timestamp=i / 30) for i, p in enumerate(sweep_order(len(recorded), 2))]
    return frames, source.intrinsics


def _session(frames, intrinsics) -> tuple[SlamSystem, dict[int, np.ndarray]]:
    """A session over `frames`, mapping off; also the trajectory as tracking left it, before the finish."""
    system = SlamSystem(SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False}), intrinsics)
    for frame in frames:
        system.push(frame)
    assert system.mode == "visual_odometry"
    system.loop_stage.wait_idle()
    system.tracking_stage.apply_loop_corrections()
    return system, {i: p.copy() for i, _, p in system.trajectory()}


def _ate(poses: dict[int, np.ndarray], frames) -> float:
    gt = {f.index: f.gt_pose for f in frames}
    keys = sorted(poses)
    return absolute_trajectory_error(np.stack([poses[k] for k in keys]), np.stack([gt[k] for k in keys]), "sim3").rmse


def test_the_finish_moves_every_frame_to_the_final_adjustment(coming_back) -> None:
    frames, intrinsics = coming_back
    system, before = _session(frames, intrinsics)
    system.finish()
    stats = system.stats()["final_adjustment"]
    assert stats["applied"] and stats["points_joined"] > 0 and stats["keyframes"] >= 10
    assert len(stats["local_scales"]) == 3 and 0.5 <= stats["local_scales"][1] <= 2.0
    refined = [e for e in system.finish_events if e.TYPE == "poses_refined"]
    assert len(refined) == 1 and refined[0].revision == system.revision
    after = {i: p for i, _, p in system.trajectory()}
    assert sorted(after) == sorted(before) and all(np.all(np.isfinite(p)) for p in after.values())
    moved = [i for i in after if not np.allclose(after[i][:3, 3], before[i][:3, 3], atol=1e-6)]
    assert len(moved) > 0.8 * len(after)
    assert _ate(after, frames) < _ate(before, frames)
    system.close()


def test_a_failing_adjustment_leaves_the_poses_and_the_finish_completes(coming_back, caplog) -> None:
    frames, intrinsics = coming_back
    system, before = _session(frames, intrinsics)

    def broken() -> dict:
        raise RuntimeError("a bug in the adjustment")

    system.tracking_stage.pose_source.keyframe_corrections = broken
    with caplog.at_level(logging.ERROR):
        system.finish()
    assert "final adjustment failed" in caplog.text
    assert not [e for e in system.finish_events if e.TYPE == "poses_refined"]
    after = {i: p for i, _, p in system.trajectory()}
    assert all(np.allclose(after[i], before[i]) for i in before)
    system.close()


def test_a_posed_rgb_session_lays_the_final_adjustment_on_the_device_poses() -> None:
    """TUM fr1/xyz frames (tests/data/tum_fr1_xyz_mini, CC BY 4.0) played three times, the motion capture sent as the
    device's poses and no depth: `pose_mode` auto chooses seeded visual odometry, whose adjusted keyframes the finish
    lays on the device's poses (its world and units: compared without alignment)."""
    source = open_source(str(DATA.parent / "tum_fr1_xyz_mini"), use_gt_depth=False, use_gt_poses=True)
    recorded = list(source)
    frames = [replace(recorded[p], index=i, timestamp=i / 30) for i, p in enumerate(sweep_order(len(recorded), 3))]
    system = SlamSystem(SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False}), source.intrinsics)
    for frame in frames:
        system.push(frame)
    system.loop_stage.wait_idle()
    system.tracking_stage.apply_loop_corrections()
    before = {i: p.copy() for i, _, p in system.trajectory()}
    system.finish()
    assert system.stats()["pose_source"] == "seeded"
    assert system.stats()["final_adjustment"]["applied"]
    assert [e for e in system.finish_events if e.TYPE == "poses_refined"]
    after = {i: p for i, _, p in system.trajectory()}
    gt = {f.index: f.gt_pose for f in frames}

    def ate(poses: dict[int, np.ndarray]) -> float:
        keys = sorted(poses)
        return absolute_trajectory_error(np.stack([poses[k] for k in keys]), np.stack([gt[k] for k in keys]),
                                         "none").rmse

    assert ate(after) < 0.9 * ate(before)
    system.close()
