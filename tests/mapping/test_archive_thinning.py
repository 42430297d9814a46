"""The archive lets go of the most redundant keyframe views first (worker.mapping.archive_thinning)."""

import numpy as np
import pytest

from worker.mapping.archive_thinning import most_redundant, thin, view_distances

FORWARD = np.array([0.0, 0.0, 1.0])


def cameras(xs: list[float], axes: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    centres = np.array([[x, 0.0, 0.0] for x in xs])
    directions = np.array(axes if axes is not None else [FORWARD] * len(xs), np.float64)
    return centres, directions / np.linalg.norm(directions, axis=1, keepdims=True)


def test_a_lingering_camera_gives_up_its_views_first_and_lone_views_stay():
    # a sweep of 10 views 0.1 apart, then the camera lingers near x = 0.5 for 5 views
    xs = [0.1 * k for k in range(10)] + [0.5 + 0.002 * k for k in range(1, 6)]
    centres, axes = cameras(xs)
    dropped = thin(centres, axes, candidates=list(range(14)), keep=9, scene_depth=1.0)
    assert len(dropped) == 5
    assert set(dropped) <= {5} | set(range(10, 14)), dropped  # only views of the lingering stretch
    kept = [i for i in range(15) if i not in dropped]
    assert {0, 1, 2, 3, 4, 6, 7, 8, 9} <= set(kept)  # every view of the sweep that only it saw


def test_a_turn_in_place_is_not_redundant_but_a_repeat_is():
    yawed = np.array([np.sin(0.5), 0.0, np.cos(0.5)])  # 29 degrees
    centres, axes = cameras([0.0, 0.0, 0.0, 1.0], [FORWARD, yawed, FORWARD, FORWARD])
    assert most_redundant(centres, axes, [0, 1, 2, 3], scene_depth=2.0) == 0  # 0 and 2 are the same view
    distances = view_distances(centres, axes, scene_depth=2.0)
    assert distances[0, 1] == pytest.approx(0.5) and distances[0, 3] == pytest.approx(0.5)
    assert np.isinf(distances[1, 1])


def test_the_scene_depth_weighs_distance_against_angle():
    yawed = np.array([np.sin(0.2), 0.0, np.cos(0.2)])
    centres, axes = cameras([0.0, 0.0, 0.5], [FORWARD, yawed, FORWARD])
    # 0.5 apart over a scene 10 away (0.05) is nearer than 0.2 rad: camera 2 and 0 are the pair
    assert most_redundant(centres, axes, [1, 2], scene_depth=10.0) == 2
    # over a scene 1 away (0.5) the turn is the nearer view
    assert most_redundant(centres, axes, [1, 2], scene_depth=1.0) == 1


def test_nothing_to_let_go_is_an_error_and_keep_is_respected():
    centres, axes = cameras([0.0, 1.0])
    with pytest.raises(ValueError):
        most_redundant(centres, axes, [], scene_depth=1.0)
    assert thin(centres, axes, [0, 1], keep=2, scene_depth=1.0) == []
    assert thin(centres, axes, [0, 1], keep=0, scene_depth=1.0) == [0, 1]
