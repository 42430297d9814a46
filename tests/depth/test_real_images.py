"""Real images: ICL-NUIM keyframes from tests/data/icl_mini (ground-truth poses; depth only to score)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.data import open_source
from worker.depth import MultiViewDepthConfig, estimate_depth, select_neighbours

ICL_MINI = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def frames():
    return list(open_source(ICL_MINI, use_gt_depth=True, use_gt_poses=True, max_frames=36))


def _K(frame) -> np.ndarray:
    i = frame.intrinsics
    return np.array([[i.fx, 0.0, i.cx], [0.0, i.fy, i.cy], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("keyframe", [10, 30])
@pytest.mark.parametrize("given_range", [True, False])
def test_icl_keyframe_depth(frames, keyframe, given_range):
    frame = frames[keyframe]
    valid = frame.depth > 0
    points = np.sort(frame.depth[valid])[:: max(1, int(valid.sum()) // 200)]  # stand-in for tracked map points
    depth_range = (0.8 * float(np.percentile(points, 2)), 1.25 * float(np.percentile(points, 98)))
    others = [i for i in range(len(frames)) if i != keyframe]
    config = MultiViewDepthConfig()
    chosen = select_neighbours(frame.pose, [frames[i].pose for i in others], config, float(np.median(points)))
    assert len(chosen) == config.num_views
    neighbours = [(frames[others[i]].image, frames[others[i]].pose) for i in chosen]
    est = estimate_depth(frame.image, _K(frame), frame.pose, neighbours, depth_range if given_range else None, config)
    scored = est.mask & valid
    l1 = float(np.abs(est.depth[scored] - frame.depth[scored]).mean())
    assert scored.sum() > 0.7 * valid.sum()
    assert l1 < 0.045  # metres: ICL is metric
