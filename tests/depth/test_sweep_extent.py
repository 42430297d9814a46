"""The epipolar sweep that decides whether a neighbour view gives parallax (worker.depth.sweep.sweep_pixels)."""

from __future__ import annotations

import numpy as np

from worker.depth.sweep import ViewGeometry, sweep_pixels

K = np.array([[200.0, 0.0, 160.0], [0.0, 200.0, 120.0], [0.0, 0.0, 1.0]])


def _view(t: np.ndarray) -> ViewGeometry:
    """A neighbour translated by t (no rotation): A = K K^-1 = I, b = K t."""
    return ViewGeometry(np.eye(3), K @ t, float(np.linalg.norm(t)))


def test_forward_motion_has_parallax_away_from_the_epipole():
    forward = sweep_pixels(_view(np.array([0.0, 0.0, -0.5])), 320, 240, near=1.0, far=10.0)
    # at the image centre (the epipole) the segment is a point; over the image the median one is long
    centre = ViewGeometry(np.eye(3), K @ np.array([0.0, 0.0, -0.5]), 0.5)
    p = np.array([160.0, 120.0, 1.0])
    ends = [centre.A @ p + centre.b / z for z in (10.0, 1.0)]
    assert np.linalg.norm(ends[0][:2] / ends[0][2] - ends[1][:2] / ends[1][2]) < 1e-9
    assert forward > 20.0


def test_sideways_motion_matches_the_disparity_formula():
    side = sweep_pixels(_view(np.array([0.1, 0.0, 0.0])), 320, 240, near=1.0, far=10.0)
    np.testing.assert_allclose(side, 200.0 * 0.1 * (1 / 1.0 - 1 / 10.0), rtol=1e-9)  # f b (1/near - 1/far)


def test_a_view_beyond_the_far_plane_gives_no_sweep():
    assert sweep_pixels(_view(np.array([0.0, 0.0, -20.0])), 320, 240, near=1.0, far=10.0) == 0.0


def test_a_view_ahead_of_the_near_plane_sweeps_the_depths_it_sees():
    """Driving forward, the next keyframe is further ahead than the nearest depths: those lie behind it, but it
    still measures the rest of the range (and is not dropped as a view without parallax)."""
    ahead = 2.0
    sweep = sweep_pixels(_view(np.array([0.0, 0.0, -ahead])), 320, 240, near=1.0, far=10.0)
    # the segments start where the view sees a point at half its reference depth: depth 2 x ahead
    expected = sweep_pixels(_view(np.array([0.0, 0.0, -ahead])), 320, 240, near=2 * ahead, far=10.0)
    assert sweep > 20.0 and np.isclose(sweep, expected)
