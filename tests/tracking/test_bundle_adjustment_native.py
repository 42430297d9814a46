"""Bundle adjustment's fast paths against their references: the compiled observation-pair sum of the reduced
camera system (worker.tracking.schur_native) against the numpy one, and the np.bincount sums against np.add.at,
on a constructed problem with outliers (the GTSAM oracle is in test_visual_odometry_parts)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from worker.tracking import schur_native
from worker.tracking.bundle_adjustment import Observations, _PairTerm, _sum_by, bundle_adjust
from worker.tracking.projection import project

K = np.array([[262.5, 0.0, 160.0], [0.0, 262.5, 120.0], [0.0, 0.0, 1.0]])


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(np.asarray(rotvec, float))[0], t
    return T


def _problem(rng, n_points=400, n_views=6):
    """Points in front of a camera moving sideways, seen by each view with probability 0.8 (0.5 px noise)."""
    points = rng.uniform([-2, -1.5, 2.5], [2, 1.5, 6], (n_points, 3))
    poses = np.stack([_pose([0.0, 0.04 * k, 0.01 * k], [0.15 * k, 0.02 * k, 0.05 * k]) for k in range(n_views)])
    slots, rows, uvs = [], [], []
    for k, pose in enumerate(poses):
        uv, z = project(points, pose, K)
        ok = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240)
        ok &= rng.random(n_points) < 0.8
        slots.append(np.full(ok.sum(), k))
        rows.append(np.flatnonzero(ok))
        uvs.append(uv[ok] + rng.normal(0, 0.5, (ok.sum(), 2)))
    uv = np.concatenate(uvs)
    return points, poses, Observations(np.concatenate(slots), np.concatenate(rows), uv, np.ones(len(uv)))


def test_sums_by_index_equal_add_at_exactly() -> None:
    rng = np.random.default_rng(3)
    index = rng.integers(0, 50, 4000)
    values = rng.normal(size=(4000, 6, 3))
    expected = np.zeros((50, 6, 3))
    np.add.at(expected, index, values)
    np.testing.assert_array_equal(_sum_by(index, values, 50), expected)  # same sums in the same order


@pytest.mark.skipif(not schur_native.available(), reason=f"no kernel: {schur_native.load_error()}")
def test_compiled_pair_sum_equals_the_numpy_one() -> None:
    rng = np.random.default_rng(4)
    n_obs, n_free = 900, 4
    Y, W = rng.normal(size=(n_obs, 6, 3)), rng.normal(size=(n_obs, 6, 3))
    pi, pj = rng.integers(0, n_obs, 5000), rng.integers(0, n_obs, 5000)
    fi, fj = rng.integers(0, n_free, 5000), rng.integers(0, n_free, 5000)
    fast = _PairTerm(pi, pj, fi, fj, n_free, native=True)(Y, W)
    reference = _PairTerm(pi, pj, fi, fj, n_free, native=False)(Y, W)
    assert np.abs(reference).max() > 10.0
    np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-10)


@pytest.mark.skipif(not schur_native.available(), reason=f"no kernel: {schur_native.load_error()}")
def test_adjustment_is_the_same_with_either_backend() -> None:
    rng = np.random.default_rng(0)
    points, poses, obs = _problem(rng)
    obs.uv[::40] += 25.0
    start = poses.copy()
    for k in range(2, len(poses)):
        start[k] = _pose(rng.normal(0, 0.01, 3), rng.normal(0, 0.03, 3)) @ poses[k]
    start_points = points + rng.normal(0, 0.05, points.shape)
    fixed = np.array([True, True, False, False, False, False])
    results = [bundle_adjust(start, fixed, start_points, obs, K, iterations=20, backend=b)
               for b in ("reference", "native")]
    assert results[0][2] and results[1][2]
    assert np.abs(results[0][0] - start).max() > 1e-3  # the solve moved the poses
    np.testing.assert_allclose(results[1][0], results[0][0], atol=1e-9)
    np.testing.assert_allclose(results[1][1], results[0][1], atol=1e-7)
