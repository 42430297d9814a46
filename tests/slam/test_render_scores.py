"""Rendering scores of a map that draws nothing (an untrained model's empty map): images are still scored, depth
L1 is reported as unavailable instead of failing the run."""

from __future__ import annotations

import numpy as np

from worker.data.synthetic import make_sequence
from worker.eval import Lpips, evaluate_renders


def test_an_empty_render_has_no_depth_score_but_an_image_score() -> None:
    frames = list(make_sequence(10_003, num_frames=3, width=48, height=36))

    def empty(_pose, _intrinsics):
        return np.zeros((36, 48, 3), np.uint8), np.zeros((36, 48), np.float32)

    scores = evaluate_renders(empty, frames, [f.gt_pose for f in frames], "none", Lpips(None, None, "off"))
    assert scores.num_frames == 3 and scores.depth_l1 is None
    assert 0 < scores.psnr < 15
