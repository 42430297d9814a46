"""The local bundle adjustment's window by covisibility (ORB-SLAM's local mapping in our terms): the keyframes that
share the most map points with the newest one move, and the other keyframes that observe those points are held
still around them (they anchor pose and scale), instead of the last N keyframes in time.

Cost: counting shared points is one sorted-membership test per keyframe of the local map (a few hundred ids each),
well under a millisecond for the 16 keyframes kept; the adjustment itself is bounded by `n_free` + `n_fixed`
keyframes and the points the free ones observe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LocalWindow:
    """Keyframe slots (ascending) the adjustment moves and those it holds still."""

    free: np.ndarray
    fixed: np.ndarray

    @property
    def slots(self) -> np.ndarray:
        """Every slot of the window, ascending."""
        return np.union1d(self.free, self.fixed)


def observed(point_ids: np.ndarray) -> np.ndarray:
    """The distinct map points (rows >= 0) one keyframe observes, sorted."""
    return np.unique(point_ids[point_ids >= 0])


def shared_points(keyframe_points: list[np.ndarray], reference: int) -> np.ndarray:
    """[F] how many map points each keyframe (its point rows, -1: none) shares with keyframe `reference`."""
    mine = observed(keyframe_points[reference])
    return np.array([int(np.isin(observed(p), mine, assume_unique=True).sum()) for p in keyframe_points], np.int64)


def _ranked(counts: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """`candidates` with a positive count, most shared first (the newer first among equals)."""
    candidates = candidates[counts[candidates] > 0]
    return candidates[np.lexsort((-candidates, -counts[candidates]))]


def covisible_window(keyframe_points: list[np.ndarray], newest: int, n_free: int, n_fixed: int,
                     min_fixed: int = 1) -> LocalWindow:
    """The local window of keyframe `newest` among keyframes whose point rows are `keyframe_points`:

    - free: `newest` and the `n_free - 1` keyframes sharing the most points with it;
    - fixed: up to `n_fixed` other keyframes observing the most of the free keyframes' points.

    When fewer than `min_fixed` keyframes qualify as fixed (a young map), the oldest free keyframes (never the
    newest) are held instead, so that the adjustment keeps a gauge."""
    count = len(keyframe_points)
    others = np.array([k for k in range(count) if k != newest], np.int64)
    shared = shared_points(keyframe_points, newest)
    free = np.sort(np.r_[newest, _ranked(shared, others)[: max(n_free - 1, 0)]]).astype(np.int64)
    points = np.unique(np.concatenate([observed(keyframe_points[k]) for k in free]))
    rest = np.setdiff1d(others, free)
    seen = np.zeros(count, np.int64)
    for k in rest:
        seen[k] = int(np.isin(observed(keyframe_points[k]), points, assume_unique=True).sum())
    fixed = np.sort(_ranked(seen, rest)[:n_fixed]).astype(np.int64)
    missing = min_fixed - len(fixed)
    if missing > 0:
        movable = free[free != newest][:missing]
        free, fixed = np.setdiff1d(free, movable), np.union1d(fixed, movable)
    return LocalWindow(free, fixed)
