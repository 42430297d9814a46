"""The local bundle adjustment's window by covisibility, on constructed keyframe observations: the keyframes that
share points with the newest move (not the last N in time), the others that see those points are held, and a young
map keeps a gauge; map points no track follows are found again by projection."""

from __future__ import annotations

import numpy as np

from worker.tracking.covisibility import covisible_window, shared_points
from worker.tracking.features import Features
from worker.tracking.reobservation import search_by_projection


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


def test_points_no_track_follows_are_found_again_by_projection():
    """A keyframe's ORB keypoints at the projections of old map points, with their descriptors, observe them again
    (search by projection); a point behind the camera, outside the image or with another descriptor does not."""
    rng = np.random.default_rng(5)
    K = np.array([[250.0, 0, 160], [0, 250.0, 120], [0, 0, 1]])
    points = np.c_[rng.uniform(-1, 1, (40, 2)), rng.uniform(2, 4, 40)]
    points[0] = [0.0, 0.0, -2.0]  # behind
    points[1] = [5.0, 0.0, 2.0]  # outside the image
    descriptors = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    uv = points[:, :2] / points[:, 2:] * 250.0 + [160, 120]
    shown = np.arange(2, 40)
    keypoints = uv[shown] + rng.normal(0, 0.5, (38, 2))  # detected a little off the projection
    orb_descriptors = descriptors[shown].copy()
    orb_descriptors[0] = ~orb_descriptors[0]  # point 2 looks different now
    clutter = rng.uniform([0, 0], [320, 240], (30, 2))  # other corners, other descriptors
    orb = Features(np.r_[keypoints, clutter].astype(np.float32),
                   np.r_[orb_descriptors, rng.integers(0, 256, (30, 32), dtype=np.uint8)].astype(np.uint8),
                   np.zeros(68, np.int32))
    rows, found = search_by_projection(points, descriptors, np.arange(40), np.eye(4), K, (320, 240), orb, 4.0, 50,
                                       0.8)
    assert rows.tolist() == list(range(3, 40))
    assert found.tolist() == list(range(1, 38))  # each point's own keypoint
    none, _ = search_by_projection(points, descriptors, np.arange(0), np.eye(4), K, (320, 240), orb, 4.0, 50, 0.8)
    assert len(none) == 0
