"""bench.pose_consistency on real ICL frames (tests/data/icl_mini): exact poses reproject tracked corners within a
fraction of a pixel; poses whose steps along the motion are off (as KITTI's) do not."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.pose_consistency import reprojection_errors
from worker.data import open_source

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


def test_exact_poses_agree_and_wrong_steps_do_not() -> None:
    src = open_source(str(DATA), use_gt_poses=True, max_frames=30)
    frames = list(src)
    K = src.intrinsics.matrix().numpy().astype(np.float64)
    exact = reprojection_errors(frames, K, step=1, triples=6)  # the frames are every third of ICL
    assert len(exact) >= 4 and np.median(exact) < 0.6
    rng = np.random.default_rng(0)
    origin = frames[0].pose[:3, 3].copy()
    for frame in frames:  # every frame's position 20 % off along the path, at random
        frame.pose = np.array(frame.pose, np.float64)
        frame.pose[:3, 3] = origin + (frame.pose[:3, 3] - origin) * (1 + 0.2 * rng.standard_normal())
    off = reprojection_errors(frames, K, step=1, triples=6)
    assert np.median(off) > 3 * np.median(exact)
