"""select_neighbours (baseline / overlap / direction) and scale_to_confident (robust median ratio)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scenes import rotation_y, translation

from worker.depth import MultiViewDepthConfig, confident_scale, scale_to_confident, select_neighbours


def _turned(x: float, degrees: float) -> np.ndarray:
    pose = rotation_y(degrees)
    pose[:3, 3] = (x, 0.0, 0.0)
    return pose


def test_select_neighbours_by_parallax_angle_and_direction():
    config = MultiViewDepthConfig(num_views=2, min_parallax=0.03, target_parallax=0.1, max_parallax=0.4,
                                  max_view_angle_deg=30)
    candidates = [
        translation(0.01),   # 0: parallax 0.005, too little
        translation(0.2),    # 1: parallax 0.1, on target, to the right
        translation(0.22),   # 2: nearly the same as 1 (same direction)
        translation(-0.18),  # 3: parallax 0.09, to the left
        translation(3.0),    # 4: parallax 1.5, too much
        _turned(0.2, 60),    # 5: good baseline, looks away (60 degrees)
    ]
    assert select_neighbours(np.eye(4), candidates, config, scene_depth=2.0) == [1, 3]
    # the same choice in other units
    scaled = [p.copy() for p in candidates]
    for p in scaled:
        p[:3, 3] *= 50.0
    assert select_neighbours(np.eye(4), scaled, config, scene_depth=100.0) == [1, 3]
    wide = config.model_copy(update={"num_views": 4, "max_view_angle_deg": 90})
    assert sorted(select_neighbours(np.eye(4), candidates, wide, scene_depth=2.0)) == [1, 2, 3, 5]


def test_select_neighbours_skips_unusable_poses(caplog):
    bad = translation(0.2)
    bad[0, 0] = np.nan
    with caplog.at_level(logging.WARNING, logger="worker.depth"):
        chosen = select_neighbours(np.eye(4), [bad, translation(-0.2), translation(0.25)], scene_depth=2.0)
    assert chosen == [1, 2] or chosen == [2, 1]
    assert "unusable poses" in caplog.text
    with caplog.at_level(logging.WARNING, logger="worker.depth"):
        assert select_neighbours(bad, [translation(0.2)]) == []
    assert "keyframe pose unusable" in caplog.text


def test_select_neighbours_without_scene_depth_prefers_median_baselines():
    candidates = [translation(x) for x in (0.001, 0.1, -0.1, 0.12, 40.0)]
    chosen = select_neighbours(np.eye(4), candidates, MultiViewDepthConfig(num_views=2))
    assert set(chosen) <= {1, 2, 3} and len(chosen) == 2


def test_scale_to_confident_recovers_the_scale_despite_outliers():
    rng = np.random.default_rng(0)
    mvs = rng.uniform(1.0, 4.0, (60, 80)).astype(np.float32)
    other = mvs / 2.5 * rng.normal(1.0, 0.02, mvs.shape).astype(np.float32)
    other[:10] = 50.0  # a band of gross model errors
    confidence = np.full(mvs.shape, 0.9, np.float32)
    confidence[40:] = 0.1  # not confident: ignored
    mvs[40:] = 1000.0
    assert confident_scale(other, mvs, confidence) == pytest.approx(2.5, rel=0.02)
    scaled = scale_to_confident(other, mvs, confidence)
    assert scaled.dtype == np.float32
    np.testing.assert_allclose(np.median(scaled[10:40] / mvs[10:40]), 1.0, rtol=0.02)


def test_scale_to_confident_without_enough_pixels_leaves_depth_alone(caplog):
    other = np.ones((20, 20), np.float32)
    with caplog.at_level(logging.WARNING, logger="worker.depth"):
        out = scale_to_confident(other, np.zeros_like(other), np.zeros_like(other))
    np.testing.assert_array_equal(out, other)
    assert "no scale" in caplog.text
    with pytest.raises(ValueError, match="shapes"):
        scale_to_confident(other, np.zeros((3, 3)), np.zeros((3, 3)))


def test_config_rejects_bad_settings():
    from pydantic import ValidationError

    for bad in ({"num_hypotheses": 32}, {"min_views": 5, "num_views": 4}, {"sgm_p1": 0.5, "sgm_p2": 0.1},
                {"target_parallax": 0.9}, {"not_a_field": 1}):
        with pytest.raises(ValidationError):
            MultiViewDepthConfig(**bad)
    assert MultiViewDepthConfig.model_validate(MultiViewDepthConfig().model_dump()) == MultiViewDepthConfig()
