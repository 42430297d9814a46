"""Degenerate input: no crash, no NaN, zero or few confident pixels and a warning that says why; malformed
arrays raise ValueError."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scenes import Scene, pinhole, rotation_y, translation

from worker.depth import MultiViewDepthConfig, estimate_depth

W, H = 96, 72
K = pinhole(W, H)
SCENE = Scene(plane_depth=2.0, boxes=[(np.array([-0.3, -0.2, 1.2]), np.array([0.2, 0.3, 1.5]))])
REF = translation(0.0)


def _views(scene: Scene, poses: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(scene.render(p, K, W, H)[0], p) for p in poses]


def _estimate(neighbours, caplog, depth_range=(1.0, 4.0), scene: Scene = SCENE, pose=REF):
    image = scene.render(REF, K, W, H)[0]
    with caplog.at_level(logging.WARNING, logger="worker.depth"):
        est = estimate_depth(image, K, pose, neighbours, depth_range, MultiViewDepthConfig())
    assert est.depth.shape == (H, W) and est.depth.dtype == np.float32
    assert np.all(np.isfinite(est.depth)) and np.all(np.isfinite(est.confidence))
    return est


def test_no_neighbour(caplog):
    est = _estimate([], caplog)
    assert est.coverage == 0.0
    assert "no usable neighbour" in caplog.text


def test_no_baseline(caplog):
    est = _estimate(_views(SCENE, [REF.copy(), REF.copy()]), caplog)
    assert est.coverage == 0.0
    assert "epipolar sweep is 0.00 px" in caplog.text and "fewer than min_views" in caplog.text


def test_no_baseline_and_no_range(caplog):
    est = _estimate(_views(SCENE, [REF.copy(), REF.copy()]), caplog, depth_range=None)
    assert est.coverage == 0.0
    assert "no baseline" in caplog.text


def test_pure_rotation(caplog):
    est = _estimate(_views(SCENE, [rotation_y(3.0), rotation_y(-3.0)]), caplog)
    assert est.coverage == 0.0
    assert "pure rotation" in caplog.text


def test_nan_keyframe_pose(caplog):
    pose = REF.copy()
    pose[0, 3] = np.nan
    est = _estimate(_views(SCENE, [translation(-0.2), translation(0.2)]), caplog, pose=pose)
    assert est.coverage == 0.0
    assert "keyframe pose unusable" in caplog.text and "NaN" in caplog.text


def test_nan_neighbour_pose_is_skipped_and_the_others_still_work(caplog):
    bad = translation(0.1)
    bad[1, 1] = np.nan
    good = _views(SCENE, [translation(-0.2), translation(0.2), translation(0, 0.15)])
    est = _estimate([good[0], (good[1][0], bad), good[1], good[2]], caplog)
    assert "neighbour 1 skipped" in caplog.text
    assert est.views_used == [0, 2, 3]
    assert est.coverage > 0.5


def test_textureless_wall(caplog):
    wall = Scene(plane_depth=2.0, textured=False)
    est = _estimate(_views(wall, [translation(-0.2), translation(0.2)]), caplog, scene=wall)
    assert est.coverage < 0.01
    assert "pixels confident" in caplog.text


def test_malformed_input_raises():
    image = SCENE.render(REF, K, W, H)[0]
    views = _views(SCENE, [translation(-0.2), translation(0.2)])
    with pytest.raises(ValueError, match="uint8"):
        estimate_depth(image.astype(np.float32), K, REF, views)
    with pytest.raises(ValueError, match="neighbour 0 image"):
        estimate_depth(image, K, REF, [(image[:10], views[0][1])])
    with pytest.raises(ValueError, match="intrinsics"):
        estimate_depth(image, np.eye(2), REF, views)
    with pytest.raises(ValueError, match="depth_range"):
        estimate_depth(image, K, REF, views, depth_range=(2.0, 1.0))
