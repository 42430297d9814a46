"""Keyframe moves that carry the local scale a final adjustment found (monocular visual odometry).

A monocular keyframe's part of the map was built at the scale the trajectory had around it when it was handed out;
odometry drifts in scale, and the final bundle adjustment takes the drift out of the poses. A rigid move from the
handed-out pose to the adjusted one leaves that part of the map at its old scale, so neighbouring parts disagree in
size. The move here is a similarity instead: around each keyframe, the ratio of the distances between the adjusted
keyframes near it to the distances between the same keyframes as handed out scales its part of the map about its
camera. Distances between every pair in the window, not the path along it: the path of noisy poses is longer than
the true one, and a camera that moves back and forth has a short chord.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

# Keyframes on each side of a keyframe whose distances measure its local scale.
SCALE_WINDOW = 4
# A window whose keyframes lie closer together than this share of the typical window's measures no scale.
MEASURABLE_EXTENT = 0.1
# The most a keyframe's part of the map is scaled either way: odometry drifts by percents between keyframes.
MAX_SCALE_CHANGE = 2.0


def local_scales(given: Mapping[int, np.ndarray], placed: Mapping[int, np.ndarray],
                 window: int = SCALE_WINDOW) -> dict[int, float]:
    """For each keyframe in both (by index), the placed over the given distances between the keyframes within
    `window` of it in index order (within `MAX_SCALE_CHANGE` either way); 1 where the given keyframes there lie
    closer together than `MEASURABLE_EXTENT` of the typical window's distances."""
    order = sorted(set(given) & set(placed))
    given_centres = np.array([given[k][:3, 3] for k in order], np.float64).reshape(-1, 3)
    placed_centres = np.array([placed[k][:3, 3] for k in order], np.float64).reshape(-1, 3)
    extents = []
    for i in range(len(order)):
        lo, hi = max(0, i - window), min(len(order), i + window + 1)
        extents.append((_pair_distances(given_centres[lo:hi]), _pair_distances(placed_centres[lo:hi])))
    typical = float(np.median([before for before, _ in extents])) if extents else 0.0
    scales = {}
    for k, (before, after) in zip(order, extents):
        if before <= MEASURABLE_EXTENT * typical or before == 0:
            scales[k] = 1.0  # a camera turning on the spot: its pose noise would read as a scale
        else:
            scales[k] = float(np.clip(after / before, 1 / MAX_SCALE_CHANGE, MAX_SCALE_CHANGE))
    return scales


def scaled_moves(given: Mapping[int, np.ndarray], placed: Mapping[int, np.ndarray],
                 scales: Mapping[int, float] | None = None) -> dict[int, np.ndarray]:
    """By keyframe index, the similarity taking each given (handed-out, rigid) pose to its placed rigid pose with its
    part of the map scaled about the camera by its scale (`local_scales` unless `scales` are given)."""
    scales = local_scales(given, placed) if scales is None else scales
    moves = {}
    for k, scale in scales.items():
        target = np.array(placed[k], np.float64)
        target[:3, :3] *= scale
        moves[k] = target @ np.linalg.inv(np.asarray(given[k], np.float64))
    return moves


def scale_spread(scales: Mapping[int, float]) -> tuple[float, float, float] | None:
    """The 5th percentile, median and 95th percentile of keyframes' local scales (None without any), for the stats."""
    if not scales:
        return None
    low, median, high = np.percentile(np.fromiter(scales.values(), np.float64), [5, 50, 95])
    return float(low), float(median), float(high)


def _pair_distances(centres: np.ndarray) -> float:
    """The sum of the distances between every pair of `centres` [N, 3]."""
    if len(centres) < 2:
        return 0.0
    differences = centres[:, None, :] - centres[None, :, :]
    return float(np.linalg.norm(differences, axis=-1).sum() / 2)
