"""The scene depth from the poses alone (worker.depth.neighbours.looked_at_depth), which chooses a keyframe's
neighbours before any depth is known: cameras around an object look at it; a sideways pan says nothing."""

from __future__ import annotations

import numpy as np

from worker.data.synthetic import look_at_c2w
from worker.depth import MultiViewDepthConfig, select_neighbours
from worker.depth.neighbours import looked_at_depth


def _orbit(radius: float, degrees: np.ndarray, target=np.zeros(3)) -> list[np.ndarray]:
    """Cameras on a horizontal circle around `target`, all looking at it."""
    poses = []
    for a in np.radians(degrees):
        position = target + radius * np.array([np.cos(a), np.sin(a), 0.3])
        poses.append(look_at_c2w(position, target - position))
    return poses


def test_cameras_around_an_object_give_its_distance() -> None:
    poses = _orbit(2.5, np.arange(0, 120, 7.5))  # 16 views, 7.5 degrees (33 cm) apart
    distance = float(np.linalg.norm(poses[0][:3, 3]))
    assert abs(looked_at_depth(poses[0], poses[1:]) - distance) < 1e-6 * distance
    scaled = [p.copy() for p in poses]
    for p in scaled:
        p[:3, 3] *= 10.0
    assert abs(looked_at_depth(scaled[0], scaled[1:]) - 10 * distance) < 1e-5 * distance


def test_a_sideways_pan_or_axes_diverging_give_nothing() -> None:
    pan = [look_at_c2w(np.array([0.1 * i, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])) for i in range(8)]
    assert looked_at_depth(pan[0], pan[1:]) is None
    outward = [look_at_c2w(np.zeros(3) + 0.0, np.array([np.cos(a), np.sin(a), 0.0]))
               for a in np.radians(np.arange(0, 80, 10))]
    for i, pose in enumerate(outward):
        pose[:3, 3] = 0.5 * pose[:3, 2] + 0.01 * i  # behind each other's axes: no meeting in front of both
    assert looked_at_depth(outward[0], outward[1:]) is None


def test_the_distance_picks_near_neighbours_where_the_median_baseline_picks_far_ones() -> None:
    poses = _orbit(2.5, np.arange(0, 120, 7.5))
    ref, candidates = poses[8], poses[:8] + poses[9:]
    config = MultiViewDepthConfig()
    baselines = [float(np.linalg.norm(p[:3, 3] - ref[:3, 3])) for p in candidates]
    by_median = select_neighbours(ref, candidates, config)
    by_axes = select_neighbours(ref, candidates, config, scene_depth=looked_at_depth(ref, candidates))
    assert max(baselines[i] for i in by_axes) < 0.35 * 2.6 < min(baselines[i] for i in by_median)
