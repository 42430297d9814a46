"""A camera's turn from whole-image intensities (worker.tracking.direct_rotation) on constructed images: a wall of
vertical stripes, where every corner tracker has an aperture problem, gives the yaw and leaves the pitch it cannot
see at the prediction; a blank image measures nothing and is refused. Then visual odometry through the synthetic
room whose fast turn over striped walls it used to lose: tracked by the alignment, said so, the turn followed."""

from __future__ import annotations

import cv2
import numpy as np

from worker.data import open_source
from worker.data.synthetic import default_intrinsics
from worker.tracking.direct_rotation import align_rotation
from worker.tracking.projection import camera_matrix
from worker.tracking.visual_odometry import VisualOdometry

INTRINSICS = default_intrinsics(320, 240)
K = camera_matrix(INTRINSICS)


def _rotation(pitch_deg: float, yaw_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    return cv2.Rodrigues(np.radians([pitch_deg, yaw_deg, roll_deg]))[0]


def _stripes(c2w: np.ndarray) -> np.ndarray:
    """uint8 image of a camera at the origin with camera-to-world rotation `c2w` inside a scene painted by the
    angle of each ray to the world's x axis (sines of unrelated periods, so that no shift repeats the pattern): to a
    camera looking down z the image is vertical stripes, slightly curved, and a turn about the x axis (pitch) leaves
    it exactly as it was, so that only the prediction can say how far the camera pitched."""
    v, u = np.mgrid[0:INTRINSICS.height, 0:INTRINSICS.width] + 0.5
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1) @ c2w.T
    angle = np.arccos(rays[..., 0] / np.linalg.norm(rays, axis=-1))
    stripes = (0.5 + 0.2 * np.sin(angle / 0.0155) + 0.12 * np.sin(angle / 0.00865 + 1.0)
               + 0.08 * np.sin(angle / 0.0355 + 2.0))
    return np.clip(255.0 * stripes, 0, 255).astype(np.uint8)


def _axis_errors_deg(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The turn that takes `truth` to `estimate` (both reference -> current camera), about the camera's x (pitch),
    y (yaw) and z (roll) axes, degrees."""
    return np.degrees(cv2.Rodrigues(estimate @ truth.T)[0].ravel())


def test_stripes_give_the_yaw_and_keep_the_unseen_pitch_at_the_prediction():
    reference = _stripes(np.eye(3))
    turned = _rotation(0.0, 7.0)  # the second camera turned 7 degrees about its vertical axis
    current = _stripes(turned)
    truth = turned.T  # reference-camera rays -> current-camera rays
    prior = _rotation(1.0, 5.0).T  # the predicted turn: 2 degrees short in yaw, 1 degree of pitch that is not there
    fit = align_rotation(reference, current, K, prior)
    assert fit.accepted, fit.reason
    error, prior_error = _axis_errors_deg(fit.rotation, truth), _axis_errors_deg(prior, truth)
    assert abs(error[1]) < 0.5  # yaw measured (the prediction was 2 degrees off)
    unseen = truth @ np.array([1.0, 0.0, 0.0])  # the world's x axis in the current camera: turns about it are invisible
    assert abs(error @ unseen - prior_error @ unseen) < 0.1  # the prediction stands there (1 degree off)
    assert abs(prior_error @ unseen) > 0.9
    assert fit.sigma_deg(np.array([0.0, 1.0, 0.0])) < 0.05 and fit.sigma_deg(unseen) > 1.0  # and it says so
    assert fit.measured_axes == 2  # yaw and roll
    assert fit.correlation > 0.95


def test_a_blank_image_is_refused():
    blank = np.full((INTRINSICS.height, INTRINSICS.width), 128, np.uint8)
    wall = _stripes(np.eye(3))
    for reference, current in ((blank, blank), (wall, blank), (blank, wall)):
        fit = align_rotation(reference, current, K, _rotation(0.0, 5.0).T)
        assert not fit.accepted and fit.reason
        assert np.all(np.isfinite(fit.rotation))


def test_unrelated_images_are_refused():
    """Another view with the same stripes, turned 40 degrees: nothing near the prediction fits."""
    fit = align_rotation(_stripes(np.eye(3)), _stripes(_rotation(0.0, 40.0)), K, _rotation(0.0, 5.0).T)
    assert not fit.accepted


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def test_visual_odometry_follows_a_fast_turn_over_striped_walls():
    """Room 10004 turns up to 7.4 degrees a frame over walls of vertical stripes from frame 42 (lost there before
    the fallback): every frame is tracked, the aligned ones say so (a `rotation_only` event with method
    `photometric`, quality at most 0.4), and the turn is followed; a blank frame after it is lost, not tracked."""
    source = open_source("synthetic://seed=10004?frames=90", use_gt_depth=False)
    frames = [source.frame(n) for n in range(50)]
    vo = VisualOdometry()
    results = [vo.track(frame, frame.intrinsics) for frame in frames]
    assert all(r.tracked and np.all(np.isfinite(r.pose)) for r in results)
    aligned = [n for n, r in enumerate(results) if any(e.TYPE == "rotation_only" and e.method ==
                                                       "photometric" for e in r.events)]
    assert aligned and min(aligned) <= 43
    for n in range(aligned[0], 50):
        if results[n].quality is not None and results[n].quality <= 0.4:  # a frame the alignment placed
            truth = frames[n - 1].gt_pose[:3, :3].T @ frames[n].gt_pose[:3, :3]
            estimate = results[n - 1].pose[:3, :3].T @ results[n].pose[:3, :3]
            assert _angle_deg(estimate @ truth.T) < 2.0, n
    blank = frames[49].__class__(50, 50 / 30.0, np.full_like(frames[49].image, 128), frames[49].intrinsics)
    last = vo.pose.copy()
    result = vo.track(blank, blank.intrinsics)
    assert not result.tracked and any(e.TYPE == "tracking_lost" for e in result.events)
    assert np.array_equal(result.pose, last)
