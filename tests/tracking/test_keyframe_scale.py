"""Keyframe moves that carry the final adjustment's local scale (worker.tracking.keyframe_scale)."""

from __future__ import annotations

import numpy as np
import pytest

from worker.tracking.keyframe_scale import local_scales, scaled_moves


def _pose(position, yaw: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[:3, 3] = position
    return pose


def _back_and_forth(count: int = 40) -> dict[int, np.ndarray]:
    """A camera sliding back and forth along x (as TUM fr1/xyz does), a keyframe every 3 frames."""
    return {3 * i: _pose([0.3 * np.sin(0.4 * i), 0.02 * i, 0.0], 0.05 * i) for i in range(count)}


def test_a_stretch_the_adjustment_made_longer_is_scaled_and_the_rest_is_not():
    given = _back_and_forth()
    placed = {}
    for k, pose in given.items():
        moved = pose.copy()
        if k >= 60:  # from keyframe 60 on, the odometry had shrunk by 10 %: adjusted, those distances grow
            moved[:3, 3] = given[60][:3, 3] + 1.1 * (pose[:3, 3] - given[60][:3, 3])
        placed[k] = moved
    scales = local_scales(given, placed)
    assert scales[0] == pytest.approx(1.0) and scales[30] == pytest.approx(1.0)
    assert scales[90] == pytest.approx(1.1) and scales[117] == pytest.approx(1.1)
    assert 1.0 < scales[63] < 1.1  # the window straddles the change


def test_noise_on_the_given_poses_does_not_read_as_a_scale():
    rng = np.random.default_rng(5)
    placed = _back_and_forth()
    given = {k: _pose(p[:3, 3] + rng.normal(0, 0.005, 3)) for k, p in placed.items()}  # 5 mm of noise
    scales = np.array(list(local_scales(given, placed).values()))
    assert np.all(np.abs(scales - 1) < 0.03)


def test_the_moves_put_each_keyframe_on_its_placed_pose_with_its_scale():
    given = _back_and_forth(12)
    placed = {k: _pose(2.0 * p[:3, 3] + [1, 2, 3], 0.3) for k, p in given.items()}  # twice the size, elsewhere
    moves = scaled_moves(given, placed)
    for k, move in moves.items():
        moved = move @ given[k]
        assert np.allclose(moved[:3, 3], placed[k][:3, 3])
        assert np.allclose(moved[:3, :3], 2.0 * placed[k][:3, :3])  # its part of the map doubles about the camera


def test_keyframes_on_one_spot_keep_their_scale():
    given = {k: _pose([1.0, 0, 0], 0.1 * k) for k in range(5)}  # a camera turning on the spot
    placed = {k: _pose([1.0, 0, 0.001 * k], 0.1 * k) for k in range(5)}
    assert local_scales(given, placed) == {k: 1.0 for k in range(5)}
    assert local_scales({}, {}) == {}


def test_a_turn_on_the_spot_within_a_walk_measures_no_scale_from_its_noise():
    rng = np.random.default_rng(6)
    walk = {k: _pose([0.1 * k, 0, 0]) for k in range(20)}
    spot = {k: _pose([2.0, 0, 0] + rng.normal(0, 1e-4, 3), 0.2 * (k - 20)) for k in range(20, 40)}
    given = {**walk, **spot}
    placed = {k: _pose(1.05 * p[:3, 3] + rng.normal(0, 1e-3, 3)) for k, p in given.items()}  # 1 mm noise after
    scales = local_scales(given, placed)
    assert scales[5] == pytest.approx(1.05, abs=0.01)
    assert all(scales[k] == 1.0 for k in range(25, 40))  # 0.1 mm apart as given: no measure
