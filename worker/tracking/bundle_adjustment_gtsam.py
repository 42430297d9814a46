"""Windowed bundle adjustment with GTSAM projection factors and a Huber kernel: the oracle of the numpy solver in
`bundle_adjustment` (same inputs, same outputs).

Keyframes marked fixed hold the gauge (a monocular map has 7 free dimensions: two fixed cameras remove them). Only
points seen by at least two of the adjusted keyframes are variables; other observations are left out.
"""

from __future__ import annotations

import gtsam
import numpy as np

from .bundle_adjustment import Observations

_X = gtsam.symbol_shorthand.X
_L = gtsam.symbol_shorthand.L


def bundle_adjust(poses: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs: Observations, K: np.ndarray,
                  iterations: int = 10, huber: float = 2.45) -> tuple[np.ndarray, np.ndarray, bool]:
    """Adjusted (poses [F, 4, 4] camera-to-world, points [P, 3]) and whether the solve ran; unchanged on failure.

    `fixed` [F] marks the keyframes held still; observations index `poses` and `points`."""
    counts = np.bincount(obs.point, minlength=len(points))
    use = counts[obs.point] >= 2
    if use.sum() < 6 or fixed.all():
        return poses, points, False
    calibration = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    kernel = gtsam.noiseModel.mEstimator.Huber.Create(huber)
    noises: dict[float, gtsam.noiseModel.Base] = {}
    for f in np.unique(obs.keyframe[use]):
        values.insert(_X(int(f)), gtsam.Pose3(poses[f]))
        if fixed[f]:
            graph.add(gtsam.NonlinearEqualityPose3(_X(int(f)), gtsam.Pose3(poses[f])))
    for p in np.unique(obs.point[use]):
        values.insert(_L(int(p)), gtsam.Point3(*points[p]))
    for f, p, uv, sigma in zip(obs.keyframe[use], obs.point[use], obs.uv[use], obs.sigma[use], strict=True):
        s = float(sigma)
        if s not in noises:
            noises[s] = gtsam.noiseModel.Robust.Create(kernel, gtsam.noiseModel.Isotropic.Sigma(2, s))
        graph.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(*uv), noises[s], _X(int(f)), _L(int(p)),
                                                      calibration))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:  # an indeterminant system (too few views of some point): keep the input
        return poses, points, False
    original_poses, original_points = poses, points
    poses, points = poses.copy(), points.copy()
    for f in np.unique(obs.keyframe[use]):
        if not fixed[f]:
            poses[f] = result.atPose3(_X(int(f))).matrix()
    for p in np.unique(obs.point[use]):
        points[p] = result.atPoint3(_L(int(p)))
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(points))):
        return original_poses, original_points, False
    return poses, points, True
