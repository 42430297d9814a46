"""Two-view initialisation on constructed geometry: the homography wins on a plane, the essential matrix on a general
scene (ORB-SLAM's score ratio), and a rotation about the optical centre gives its rotation but no map."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from worker.tracking.model_selection import HOMOGRAPHY_RATIO, rotation_of_homography, score_models
from worker.tracking.projection import invert_pose, project
from worker.tracking.two_view import two_view_from_matches
from worker.tracking.vo_config import VisualOdometryConfig

K = np.array([[262.5, 0.0, 160.0], [0.0, 262.5, 120.0], [0.0, 0.0, 1.0]])
CONFIG = VisualOdometryConfig()


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(np.asarray(rotvec, float))[0], t
    return T


def _matches(points: np.ndarray, pose_b: np.ndarray, rng: np.random.Generator, noise: float = 0.5):
    """Pixels of `points` in camera a (the origin) and camera b (c2w pose_b), noisy, both inside the image."""
    uv_a, za = project(points, np.eye(4), K)
    uv_b, zb = project(points, pose_b, K)
    inside = (za > 0) & (zb > 0)
    for uv in (uv_a, uv_b):
        inside &= (uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240)
    uv_a, uv_b = uv_a[inside], uv_b[inside]
    return uv_a + rng.normal(0, noise, uv_a.shape), uv_b + rng.normal(0, noise, uv_b.shape)


def _plane(rng, n=300) -> np.ndarray:
    """Points on a tilted wall about 3 m ahead."""
    x, y = rng.uniform(-2.0, 2.0, n), rng.uniform(-1.5, 1.5, n)
    return np.stack([x, y, 3.0 + 0.4 * x - 0.2 * y], axis=1)


def _volume(rng, n=300) -> np.ndarray:
    return rng.uniform([-2.0, -1.5, 1.5], [2.0, 1.5, 6.0], (n, 3))


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def _check_motion(attempt, truth: np.ndarray) -> None:
    assert attempt.map is not None, attempt.reason
    pose = attempt.map.pose_b
    # Before any bundle adjustment: OpenCV's five-point RANSAC alone is off by up to 2 degrees here.
    assert _angle_deg(pose[:3, :3] @ truth[:3, :3].T) < 2.5
    t, t_true = pose[:3, 3], truth[:3, 3]
    assert np.degrees(np.arccos(t @ t_true / np.linalg.norm(t) / np.linalg.norm(t_true))) < 10.0
    assert np.median(attempt.map.points[:, 2]) == pytest.approx(1.0)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_wall_with_a_few_things_before_it_is_initialised_from_the_homography(seed):
    rng = np.random.default_rng(seed)
    truth = _pose([0.02, -0.05, 0.01], [0.4, 0.05, 0.1])
    points = np.concatenate([_plane(rng, 255), _volume(rng, 45)])  # 85 % on the wall
    pa, pb = _matches(points, truth, rng)
    attempt = two_view_from_matches(pa, pb, K, CONFIG, np.ones(len(pa)), np.ones(len(pb)))
    assert attempt.model == "homography" and attempt.score_ratio > HOMOGRAPHY_RATIO
    _check_motion(attempt, truth)  # the points off the wall chose between the homography's two motions


@pytest.mark.parametrize("seed", range(6))
def test_a_bare_plane_never_gives_the_wrong_motion(seed):
    """A plane's homography has two physical motions; where the matches cannot tell them apart, no map is made
    (ORB-SLAM's rule) rather than the wrong one."""
    rng = np.random.default_rng(seed)
    truth = _pose([0.02, -0.05, 0.01], [0.4, 0.05, 0.1])
    pa, pb = _matches(_plane(rng), truth, rng)
    attempt = two_view_from_matches(pa, pb, K, CONFIG, np.ones(len(pa)), np.ones(len(pb)))
    assert attempt.model == "homography" and attempt.score_ratio > HOMOGRAPHY_RATIO
    if attempt.map is None:
        assert attempt.reason.startswith("ambiguous motion") and attempt.rotation is None
    else:
        _check_motion(attempt, truth)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_general_scene_is_initialised_from_the_essential_matrix(seed):
    rng = np.random.default_rng(seed)
    truth = _pose([0.02, -0.05, 0.01], [0.4, 0.05, 0.1])
    pa, pb = _matches(_volume(rng), truth, rng)
    attempt = two_view_from_matches(pa, pb, K, CONFIG, np.ones(len(pa)), np.ones(len(pb)))
    assert attempt.model == "essential" and attempt.score_ratio < HOMOGRAPHY_RATIO
    _check_motion(attempt, truth)


def test_a_pure_rotation_gives_its_rotation_and_no_map():
    rng = np.random.default_rng(3)
    truth = _pose([0.03, 0.12, -0.02], [0.0, 0.0, 0.0])  # 7 degrees about the optical centre
    pa, pb = _matches(_volume(rng), truth, rng)
    attempt = two_view_from_matches(pa, pb, K, CONFIG, np.ones(len(pa)), np.ones(len(pb)))
    assert attempt.map is None and attempt.rotation_only, attempt.reason
    assert _angle_deg(attempt.rotation @ truth[:3, :3].T) < 0.2


def test_scores_count_symmetric_transfer_errors():
    rng = np.random.default_rng(4)
    truth = _pose([0.0, 0.05, 0.0], [0.0, 0.0, 0.0])
    pa, pb = _matches(_volume(rng), truth, rng, noise=0.0)
    w2c = invert_pose(truth)
    H = K @ w2c[:3, :3] @ np.linalg.inv(K)
    exact = score_models(H, None, pa, pb)
    assert exact.inliers_h.all() and exact.homography == pytest.approx(2 * 5.991 * len(pa))
    assert exact.ratio == 1.0
    shifted = score_models(H, None, pa, pb + np.array([2.0, 0.0]))  # 4 px^2 each way: inside the bound, less score
    assert shifted.inliers_h.all() and shifted.homography < exact.homography
    far = score_models(H, None, pa, pb + np.array([3.0, 0.0]))  # 9 px^2: outside
    assert not far.inliers_h.any() and far.homography == 0.0
    assert _angle_deg(rotation_of_homography(-3.0 * H, K) @ w2c[:3, :3].T) < 1e-6
