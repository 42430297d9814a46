"""The parts of monocular VO against oracles: numpy bundle adjustment vs GTSAM, the robust pose refinement vs
OpenCV's PnP refinement, guided matching on constructed projections, two-view initialisation and triangulation on
rendered synthetic views with known poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from worker.data.synthetic import SyntheticScene, default_intrinsics
from worker.tracking import bundle_adjustment_gtsam
from worker.tracking.bundle_adjustment import Observations, bundle_adjust, reprojection_chi2
from worker.tracking.features import Features, OrbExtractor
from worker.tracking.matching import match_by_projection, ratio_matches
from worker.tracking.pose_optimization import optimize_pose
from worker.tracking.projection import camera_matrix, invert_pose, project, to_camera
from worker.tracking.triangulation import good_points, triangulate
from worker.tracking.two_view import initialise_two_view
from worker.tracking.vo_config import VisualOdometryConfig

K = np.array([[262.5, 0.0, 160.0], [0.0, 262.5, 120.0], [0.0, 0.0, 1.0]])


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(np.asarray(rotvec, float))[0], t
    return T


def _scene(rng, n_points=400, n_views=5):
    points = rng.uniform([-2, -1.5, 2.5], [2, 1.5, 6], (n_points, 3))
    poses = np.stack([_pose([0.0, 0.04 * k, 0.01 * k], [0.15 * k, 0.02 * k, 0.05 * k]) for k in range(n_views)])
    return points, poses


def _observe(rng, points, poses, noise=0.5, keep=0.8):
    slots, rows, uvs = [], [], []
    for k, pose in enumerate(poses):
        uv, z = project(points, pose, K)
        ok = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240)
        ok &= rng.random(len(points)) < keep
        slots.append(np.full(ok.sum(), k))
        rows.append(np.flatnonzero(ok))
        uvs.append(uv[ok] + rng.normal(0, noise, (ok.sum(), 2)))
    uv = np.concatenate(uvs)
    return Observations(np.concatenate(slots), np.concatenate(rows), uv, np.ones(len(uv)))


def test_bundle_adjustment_matches_gtsam_and_reduces_error():
    rng = np.random.default_rng(0)
    points, poses = _scene(rng)
    obs = _observe(rng, points, poses)
    obs.uv[::40] += 25.0  # gross outliers: the Huber kernel must keep them from dragging the solution
    start = poses.copy()
    for k in range(2, len(poses)):
        start[k] = _pose(rng.normal(0, 0.01, 3), rng.normal(0, 0.03, 3)) @ poses[k]
    start_points = points + rng.normal(0, 0.05, points.shape)
    fixed = np.array([True, True, False, False, False])
    ours, our_points, ran = bundle_adjust(start, fixed, start_points, obs, K, iterations=20)
    ref, ref_points, ref_ran = bundle_adjustment_gtsam.bundle_adjust(start, fixed, start_points, obs, K, 20)
    assert ran and ref_ran
    np.testing.assert_array_equal(ours[fixed], start[fixed])
    for k in range(2, len(poses)):
        assert np.linalg.norm(ours[k, :3, 3] - ref[k, :3, 3]) < 2e-3
        assert np.linalg.norm(ours[k, :3, 3] - poses[k, :3, 3]) < np.linalg.norm(start[k, :3, 3] - poses[k, :3, 3])
    inliers = np.ones(len(obs.point), bool)
    inliers[::40] = False
    ours_chi2 = np.median(reprojection_chi2(ours, our_points, obs, K)[inliers])
    ref_chi2 = np.median(reprojection_chi2(ref, ref_points, obs, K)[inliers])
    assert ours_chi2 == pytest.approx(ref_chi2, rel=0.05)
    assert ours_chi2 < 1.0  # noise of 0.5 px: median chi2 of a 2-dof residual ~ 0.35


def test_bundle_adjustment_leaves_underdetermined_input_alone():
    rng = np.random.default_rng(1)
    points, poses = _scene(rng, n_views=2)
    obs = _observe(rng, points, poses)
    same, same_points, ran = bundle_adjust(poses, np.array([True, True]), points, obs, K)
    assert not ran and same is poses and same_points is points


def test_pose_refinement_agrees_with_opencv_and_rejects_outliers():
    rng = np.random.default_rng(2)
    points = rng.uniform([-2, -1.5, 2], [2, 1.5, 5], (300, 3))
    truth = _pose([0.05, -0.1, 0.02], [0.1, -0.05, 0.2])
    uv, _ = project(points, truth, K)
    uv += rng.normal(0, 0.5, uv.shape)
    uv[:40] += rng.uniform(15, 60, (40, 2)) * rng.choice([-1, 1], (40, 2))
    pose, inlier = optimize_pose(np.eye(4), points, uv, np.ones(len(uv)), K)
    assert not inlier[:40].any() and inlier[40:].mean() > 0.95
    w2c = invert_pose(truth)
    rvec, tvec = cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3].copy()
    rvec, tvec = cv2.solvePnPRefineLM(points[40:], uv[40:], K, None, rvec, tvec)
    oracle = np.eye(4)
    oracle[:3, :3], oracle[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    np.testing.assert_allclose(pose, invert_pose(oracle), atol=2e-3)


def test_guided_matching_finds_the_right_keypoint_within_the_radius():
    rng = np.random.default_rng(3)
    keypoints = rng.uniform([0, 0], [320, 240], (200, 2)).astype(np.float32)
    descriptors = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    features = Features(keypoints, descriptors, np.zeros(200, np.int32))
    target = rng.permutation(200)[:50]
    uv = keypoints[target] + rng.normal(0, 2.0, (50, 2)).astype(np.float32)
    found = match_by_projection(uv, descriptors[target], np.full(50, 8.0), features, max_distance=64, ratio=0.8)
    np.testing.assert_array_equal(found, target)
    far = match_by_projection(uv + 40.0, descriptors[target], np.full(50, 8.0), features, 64, 0.8)
    assert (far != target).all()  # out of the radius: the true keypoint is never taken


@pytest.fixture(scope="module")
def synthetic_pair():
    scene = SyntheticScene(10_003)
    intrinsics = default_intrinsics(320, 240)
    poses = scene.camera_path(300, revisit=False)
    extractor = OrbExtractor(VisualOdometryConfig())
    views = []
    for n in (0, 10):
        rgb, depth = scene.render(poses[n], intrinsics)
        views.append((extractor.extract(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)), depth, poses[n]))
    return views, camera_matrix(intrinsics), extractor


def test_two_view_initialisation_recovers_the_relative_motion(synthetic_pair):
    (fa, _, pa), (fb, _, pb), K_syn, extractor = *synthetic_pair[0], *synthetic_pair[1:]
    config = VisualOdometryConfig()
    attempt = initialise_two_view(fa, fb, K_syn, config, extractor.level_sigmas(fa.octaves),
                                  extractor.level_sigmas(fb.octaves))
    assert attempt.map is not None, attempt.reason
    two = attempt.map
    truth = invert_pose(pa) @ pb  # camera b in camera a's frame
    rotation_error = np.degrees(np.linalg.norm(cv2.Rodrigues(two.pose_b[:3, :3] @ truth[:3, :3].T)[0]))
    t_est, t_true = two.pose_b[:3, 3], truth[:3, 3]
    direction_error = np.degrees(np.arccos(t_est @ t_true / np.linalg.norm(t_est) / np.linalg.norm(t_true)))
    assert rotation_error < 1.5 and direction_error < 10.0
    assert np.median(two.points[:, 2]) == pytest.approx(1.0)


def test_two_view_initialisation_refuses_a_pure_rotation(synthetic_pair):
    (fa, _, _), _ = synthetic_pair[0]
    K_syn, extractor = synthetic_pair[1], synthetic_pair[2]
    # The same view turned by 3 degrees about the optical centre: an image warp by K R K^-1, no parallax.
    H = K_syn @ cv2.Rodrigues(np.array([0.0, np.radians(3.0), 0.0]))[0] @ np.linalg.inv(K_syn)
    uv = cv2.perspectiveTransform(fa.keypoints[None].astype(np.float64), H)[0].astype(np.float32)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240)
    rotated = Features(uv[inside], fa.descriptors[inside], fa.octaves[inside])
    config = VisualOdometryConfig(init_min_matches=20, init_min_points=20)
    attempt = initialise_two_view(fa, rotated, K_syn, config, extractor.level_sigmas(fa.octaves),
                                  extractor.level_sigmas(rotated.octaves))
    assert attempt.map is None and attempt.matches >= 20


def test_triangulation_with_true_poses_matches_rendered_depth(synthetic_pair):
    (fa, depth_a, pa), (fb, _, pb) = synthetic_pair[0]
    K_syn, extractor = synthetic_pair[1], synthetic_pair[2]
    ia, ib = ratio_matches(fa.descriptors, fb.descriptors, 0.8, 64)
    uv_a, uv_b = fa.keypoints[ia].astype(np.float64), fb.keypoints[ib].astype(np.float64)
    points = triangulate(pa, pb, uv_a, uv_b, K_syn)
    ok = good_points(points, pa, pb, uv_a, uv_b, extractor.level_sigmas(fa.octaves[ia]),
                     extractor.level_sigmas(fb.octaves[ib]), K_syn, 5.991, 0.5)
    assert ok.sum() >= 20
    z = to_camera(points[ok], pa)[:, 2]
    pixel = uv_a[ok].astype(int)
    truth = depth_a[pixel[:, 1], pixel[:, 0]]
    assert np.median(np.abs(z / truth - 1.0)) < 0.1
