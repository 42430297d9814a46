"""The local bundle adjustment's window by covisibility, on constructed keyframe observations: the keyframes that
share points with the newest move (not the last N in time), the others that see those points are held, and a young
map keeps a gauge."""

from __future__ import annotations

import numpy as np

from worker.tracking.covisibility import covisible_window, shared_points


def _rows(*ranges: tuple[int, int]) -> np.ndarray:
    """Point rows of one keyframe (with an unmatched -1 feature, as keyframes have)."""
    return np.r_[np.concatenate([np.arange(a, b) for a, b in ranges]), -1].astype(np.int64)


def test_the_window_is_the_keyframes_that_share_points_not_the_last_ones():
    # Keyframes 0-1 saw a place (points 0-99) the camera comes back to at keyframe 6; keyframes 2-5 looked
    # elsewhere (points 200-399), keyframe 5 also sees a few of the points keyframe 0-1 share with 6.
    points = [_rows((0, 100)), _rows((0, 80), (100, 120)), _rows((200, 300)), _rows((250, 350)),
              _rows((300, 400)), _rows((350, 400), (90, 95)), _rows((0, 95), (500, 520))]
    assert shared_points(points, 6).tolist() == [95, 80, 0, 0, 0, 5, 115]
    window = covisible_window(points, newest=6, n_free=3, n_fixed=2)
    assert window.free.tolist() == [0, 1, 6]  # the last three in time would be 4, 5, 6
    assert window.fixed.tolist() == [5]  # the only other keyframe observing the free keyframes' points
    assert set(window.slots.tolist()) == {0, 1, 5, 6}


def test_fixed_neighbours_are_those_observing_most_of_the_free_points():
    chain = [_rows((10 * k, 10 * k + 60)) for k in range(8)]  # each keyframe shares 50 points with the next
    window = covisible_window(chain, newest=7, n_free=3, n_fixed=2)
    assert window.free.tolist() == [5, 6, 7]
    assert window.fixed.tolist() == [3, 4]  # 4 sees 50 of their points, 3 sees 40, 2 only 30
    assert not set(window.free) & set(window.fixed)


def test_a_young_map_holds_its_oldest_keyframes_for_a_gauge():
    points = [_rows((0, 50)), _rows((0, 50)), _rows((0, 50))]
    window = covisible_window(points, newest=2, n_free=8, n_fixed=2, min_fixed=2)
    assert window.fixed.tolist() == [0, 1] and window.free.tolist() == [2]
    lone = covisible_window([_rows((0, 10)), _rows((20, 30))], newest=1, n_free=8, n_fixed=2, min_fixed=1)
    assert lone.free.tolist() == [1] and lone.fixed.tolist() == []  # nothing shared: nothing to hold
