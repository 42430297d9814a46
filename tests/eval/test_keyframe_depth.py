"""Keyframe depth against a sensor's (worker.eval.keyframe_depth): the scores on real Kinect depth, the map's
keyframe depths in world units, and `flashmono run`'s metrics for a posed RGB run of real TUM frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from worker.config import SlamConfig
from worker.eval.keyframe_depth import keyframe_depth_scores
from worker.geometry import make_sim3
from worker.mapping import GaussianMap, Surfels
from worker.offline import run_sequence

TUM = Path(__file__).parents[1] / "data" / "tum_fr1_xyz_mini"


def _sensor(index: int) -> np.ndarray:
    raw = cv2.imread(str(TUM / "depth" / f"{index:06d}.png"), cv2.IMREAD_UNCHANGED)
    return raw.astype(np.float32) / 1000.0


def test_a_scaled_partial_depth_scores_its_coverage_and_only_the_unscaled_error():
    sensor = {i: _sensor(i) for i in (40, 50, 60)}
    rng = np.random.default_rng(3)
    depths = {}
    for i, truth in sensor.items():
        kept = rng.random(truth.shape) < 0.5
        depths[i] = np.where(kept, 1.1 * truth, 0).astype(np.float32)  # half the pixels, 10 % too far
    scores = keyframe_depth_scores(depths, sensor, metric=True)
    assert scores.keyframes == 3
    assert 0.45 < scores.coverage < 0.55 and scores.meeting_targets == 0.0  # under 70 % coverage
    assert scores.l1 < 1e-3  # the median scaling takes the 10 % out
    mean_depth = np.mean([t[t > 0].mean() for t in sensor.values()])
    assert scores.l1_unscaled == pytest.approx(0.1 * mean_depth, rel=0.05)
    assert keyframe_depth_scores(depths, sensor).l1_unscaled is None  # units not metres: no unscaled figure


def test_noise_beyond_ten_centimetres_misses_the_target_and_unknown_frames_are_skipped():
    truth = _sensor(70)
    rng = np.random.default_rng(4)
    good = np.where(truth > 0, truth + rng.normal(0, 0.02, truth.shape), 0).astype(np.float32)
    bad = np.where(truth > 0, truth + rng.normal(0, 0.4, truth.shape).clip(-0.9 * truth, None), 0)
    scores = keyframe_depth_scores({1: good, 2: bad.astype(np.float32), 3: good}, {1: truth, 2: truth})
    assert scores.keyframes == 2 and scores.meeting_targets == 0.5  # frame 3 has no sensor depth
    assert scores.coverage == pytest.approx(1.0)
    assert keyframe_depth_scores({3: good}, {1: truth}) is None


def test_the_map_gives_keyframe_depths_in_world_units():
    gmap = GaussianMap()
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    depth = torch.full((48, 64), 2.0)
    image = torch.full((48, 64, 3), 0.5)
    scaled = make_sim3(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 3.0)
    gmap.add_keyframe(7, scaled, K, image, Surfels.empty(), depth=depth)  # a Sim(3) keyframe: camera units x 3
    gmap.add_keyframe(8, torch.eye(4, dtype=torch.float64), K, image, Surfels.empty())  # no depth
    depths = gmap.keyframe_depths()
    assert set(depths) == {7} and np.allclose(depths[7], 6.0)


def test_a_posed_rgb_run_scores_its_keyframe_depth_and_an_rgbd_run_does_not(tmp_path: Path):
    config = SlamConfig.preset("test", mapping={"final_refine_passes": 0})
    posed = run_sequence(TUM, tmp_path / "posed", config, use_gt_poses=True, max_frames=24, resize=(160, 120))
    scores = posed["keyframe_depth"]
    assert scores is not None and scores["keyframes"] >= 1
    assert 0 < scores["coverage"] <= 1 and np.isfinite(scores["l1"]) and scores["l1_unscaled"] is not None
    rgbd = run_sequence(TUM, tmp_path / "rgbd", config, use_gt_depth=True, use_gt_poses=True, max_frames=8,
                        resize=(160, 120))
    assert rgbd["keyframe_depth"] is None
