"""Rotation from point tracks alone (worker.tracking.rotation_only) on constructed geometry, and visual odometry
through a turn in place too fast for new points to be triangulated: tracked by the rotation, said so, the position
held, never lost and never a pose that stands still while the view turns."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from worker.data.frame import Frame
from worker.data.synthetic import SyntheticScene, default_intrinsics
from worker.tracking.projection import camera_matrix
from worker.tracking.rotation_only import bearings, fit_rotation, position_given_rotation
from worker.tracking.visual_odometry import VisualOdometry

INTRINSICS = default_intrinsics(320, 240)
K = camera_matrix(INTRINSICS)


def _rotation(axis: list[float], degrees: float) -> np.ndarray:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return cv2.Rodrigues(axis * np.radians(degrees))[0]


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def _points(rng: np.random.Generator, n: int, depth: tuple[float, float]) -> np.ndarray:
    """World points in front of a camera at the origin looking down +z."""
    z = rng.uniform(*depth, n)
    return np.column_stack([rng.uniform(-0.6, 0.6, n) * z, rng.uniform(-0.45, 0.45, n) * z, z])


def _pixels(points: np.ndarray, R_cw: np.ndarray, centre: np.ndarray) -> np.ndarray:
    cam = (points - centre) @ R_cw  # world -> camera for a camera-to-world rotation R_cw
    return np.column_stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]])


def test_the_rotation_of_a_turn_in_place_is_found_despite_wrong_tracks():
    rng = np.random.default_rng(3)
    points = _points(rng, 200, (1.0, 4.0))
    turn = _rotation([0.2, 1.0, 0.1], 6.0)  # camera-to-world of the second camera
    before, after = _pixels(points, np.eye(3), np.zeros(3)), _pixels(points, turn, np.zeros(3))
    after += rng.normal(0, 0.3, after.shape)
    wrong = rng.choice(len(points), 60, replace=False)  # 30 % of the tracks slipped
    after[wrong] += rng.uniform(5, 30, (len(wrong), 2)) * rng.choice([-1, 1], (len(wrong), 2))
    found = fit_rotation(bearings(before, K), bearings(after, K), 1.5 / K[0, 0])
    assert found is not None
    R, inlier = found
    assert _angle_deg(R @ turn) < 0.05  # R takes first-camera rays to second-camera rays: R = turn^T
    assert not inlier[wrong].any() and inlier.sum() >= 0.95 * (len(points) - len(wrong))


def test_parallax_breaks_the_rotation_model():
    """A camera that moves sideways by 10 % of the scene depth: no single rotation explains near and far points."""
    rng = np.random.default_rng(4)
    points = _points(rng, 200, (0.8, 4.0))
    turn = _rotation([0.0, 1.0, 0.0], 3.0)
    before = _pixels(points, np.eye(3), np.zeros(3))
    after = _pixels(points, turn, np.array([0.2, 0.0, 0.0]))
    R, inlier = fit_rotation(bearings(before, K), bearings(after, K), 1.5 / K[0, 0])
    assert inlier.mean() < 0.5


def test_the_position_comes_from_map_points_given_the_rotation():
    rng = np.random.default_rng(5)
    points = _points(rng, 30, (1.0, 3.0))
    R = _rotation([0.3, 1.0, 0.0], 10.0)
    centre = np.array([0.05, -0.02, 0.1])
    uv = _pixels(points, R, centre) + rng.normal(0, 0.2, (len(points), 2))
    uv[:4] += 25.0  # four wrong tracks
    found = position_given_rotation(R, points, bearings(uv, K), 3.0 / K[0, 0])
    assert found is not None
    estimate, inlier = found
    assert np.linalg.norm(estimate - centre) < 0.005
    assert not inlier[:4].any() and inlier[4:].all()
    assert position_given_rotation(R, points[:2], bearings(uv[:2], K), 3.0 / K[0, 0]) is None


def _move_then_turn(moves: int, turns: int, step_deg: float, walk: int = 0) -> list[Frame]:
    """A synthetic room's camera that follows its path (a map is made), then turns in place about its vertical
    axis `step_deg` per frame (the map's points soon leave the view and the turn gives new ones no parallax), then
    walks `walk` frames straight ahead, 2 cm per frame."""
    scene = SyntheticScene(10003)
    poses = list(scene.camera_path(90)[:moves])
    for k in range(1, turns + 1):
        pose = poses[moves - 1].copy()
        pose[:3, :3] = pose[:3, :3] @ _rotation([0.0, 1.0, 0.0], step_deg * k)
        poses.append(pose)
    turned = poses[-1]
    for k in range(1, walk + 1):
        pose = turned.copy()
        pose[:3, 3] += 0.02 * k * turned[:3, 2]
        poses.append(pose)
    return [Frame(n, n / 30.0, scene.render(pose, INTRINSICS)[0], INTRINSICS, gt_pose=pose)
            for n, pose in enumerate(poses)]


MOVES, TURNS, WALK = 24, 14, 16


@pytest.fixture(scope="module")
def turn_and_walk() -> list[Frame]:
    return _move_then_turn(MOVES, TURNS, 5.0, WALK)


def test_a_fast_turn_in_place_is_tracked_by_its_rotation_and_said_so(turn_and_walk):
    moves, turns = MOVES, TURNS
    frames = turn_and_walk[:moves + turns]
    results = []
    bridged = VisualOdometry()
    for frame in frames:
        results.append(bridged.track(frame, frame.intrinsics))
        assert np.all(np.isfinite(results[-1].pose))
    events = [(n, e.TYPE) for n, r in enumerate(results) for e in r.events]
    assert not any(kind == "tracking_lost" for _, kind in events), events
    rotation_runs = [n for n, kind in events if kind == "rotation_only"]
    assert rotation_runs and rotation_runs[0] >= moves, events  # only once the map points left the view
    start = moves - 1
    for n in range(moves, len(frames)):
        truth = frames[start].gt_pose[:3, :3].T @ frames[n].gt_pose[:3, :3]
        estimate = results[start].pose[:3, :3].T @ results[n].pose[:3, :3]
        assert _angle_deg(estimate @ truth.T) < 1.0, n  # the turn is followed
        assert results[n].tracked and 0.0 < results[n].quality <= 0.5 or n < rotation_runs[0]
    # the position barely moves (scene depth ~ 1 in the map's units): held or measured, no scale collapse
    assert np.linalg.norm(results[-1].pose[:3, 3] - results[start].pose[:3, 3]) < 0.1
    # Without the rotation bridge (and the photometric fallback behind it) the same frames are lost.
    plain = VisualOdometry(bridged.config.model_copy(update={"rotation_bridge": False, "direct_fallback": False}))
    lost = [e for f in frames for e in plain.track(f, f.intrinsics).events if e.TYPE == "tracking_lost"]
    assert lost


def test_walking_on_after_the_turn_ends_the_rotation_only_run(turn_and_walk):
    """Translation after the turn shows as parallax against the run's keyframe: the frames are then lost (and a map
    restarts), never tracked with a held position while the camera walks away."""
    vo = VisualOdometry()
    results = [vo.track(frame, frame.intrinsics) for frame in turn_and_walk]
    walking = results[MOVES + TURNS:]
    held = [n for n, r in enumerate(walking) if r.tracked and r.quality is not None and 0.0 < r.quality <= 0.5]
    assert len(held) <= 4, held  # noticed within a few frames (2 cm each)
    assert any(e.TYPE == "tracking_lost" for r in walking for e in r.events)
