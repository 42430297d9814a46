"""RGB-only frames through the engine: visual odometry tracks, keyframes get multi-view depth on its poses, the map
explains the views, and a snapshot taken mid-run continues exactly (real ICL frames, tests/data/icl_mini)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "icl_mini"
FRAMES = 24


@pytest.fixture(scope="module")
def rgb_frames():
    src = open_source(str(DATA), use_gt_depth=False, use_gt_poses=False, max_frames=FRAMES)
    return list(src), src.intrinsics


def _config() -> SlamConfig:
    return SlamConfig.preset("rgbd", threaded=False, mapping={"refine_iterations": 1, "final_refine_passes": 0})


def test_rgb_only_frames_are_tracked_and_mapped(rgb_frames) -> None:
    frames, intr = rgb_frames
    system = SlamSystem(_config(), intr)
    results = [system.push(f) for f in frames]
    system.finish()
    assert system.mode == "visual_odometry" and system.depth_source == "mvs" and system.tracker is None
    assert all(np.all(np.isfinite(r.pose)) for r in results)
    poses = np.stack([p for _, _, p in system.trajectory()])
    gt = np.stack([f.gt_pose for f in frames])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    assert absolute_trajectory_error(poses, gt, "sim3").rmse < 0.05 * path
    assert system.num_gaussians > 1000
    k = len(frames) // 2
    rgb, _ = system.render_view(poses[k], intr.matrix(), intr.width, intr.height)
    assert float(np.abs(rgb.astype(np.float32) - frames[k].image).mean()) < 30  # the map explains the view
    system.close()


def test_snapshot_continues_the_visual_odometry(rgb_frames) -> None:
    frames, intr = rgb_frames
    straight = SlamSystem(_config(), intr)
    expected = [straight.push(f).pose for f in frames]
    first = SlamSystem(_config(), intr)
    for f in frames[:14]:
        first.push(f)
    restored = SlamSystem.restore(first.snapshot())
    assert restored.tracking == "visual_odometry"
    got = [restored.push(f).pose for f in frames[14:]]
    for a, b in zip(got, expected[14:]):
        np.testing.assert_allclose(a, b, atol=1e-6)
    for system in (straight, first, restored):
        system.close()
