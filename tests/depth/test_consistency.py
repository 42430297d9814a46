"""cross_check: geometric agreement of two depth maps of the same scene seen from two poses."""

from __future__ import annotations

import numpy as np
from scenes import Scene, pinhole, translation

from worker.depth.consistency import cross_check

W, H = 96, 72
K = pinhole(W, H)
SCENE = Scene(plane_depth=2.0, boxes=[(np.array([-0.3, -0.2, 1.2]), np.array([0.2, 0.3, 1.5]))])


def test_true_depths_agree_and_a_wrong_surface_conflicts():
    pose_a, pose_b = translation(0.0), translation(0.25)
    depth_a, depth_b = SCENE.render(pose_a, K, W, H)[1], SCENE.render(pose_b, K, W, H)[1]
    agree, conflict = cross_check(depth_a, pose_a, depth_b, pose_b, K)
    assert agree.mean() > 0.75 and conflict.mean() < 0.01  # the rest: outside b, or hidden behind the box in b
    wrong = depth_a.copy()
    wrong[:, -20:] *= 0.8  # a surface in front of the plane that b does not see: b looks through it
    agree, conflict = cross_check(wrong, pose_a, depth_b, pose_b, K)
    assert conflict[:, -20:].mean() > 0.9 and agree[:, -20:].mean() < 0.05
    assert conflict[:, :-30].mean() < 0.01


def test_scale_free():
    pose_a, pose_b = translation(0.0), translation(0.25)
    depth_a, depth_b = SCENE.render(pose_a, K, W, H)[1], SCENE.render(pose_b, K, W, H)[1]
    big_b = pose_b.copy()
    big_b[:3, 3] *= 100.0
    agree, _ = cross_check(depth_a, pose_a, depth_b, pose_b, K)
    agree_big, _ = cross_check(depth_a * 100.0, pose_a, depth_b * 100.0, big_b, K)
    assert np.array_equal(agree, agree_big)
