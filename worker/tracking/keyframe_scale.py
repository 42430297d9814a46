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

import logging
from collections.abc import Mapping

import numpy as np

log = logging.getLogger(__name__)

# Keyframes on each side of a keyframe whose distances measure its local scale.
SCALE_WINDOW = 4


def local_scales(given: Mapping[int, np.ndarray], placed: Mapping[int, np.ndarray],
                 window: int = SCALE_WINDOW) -> dict[int, float]:
    """For each keyframe in both (by index), the placed over the given distances between the keyframes within
    `window` of it in index order; 1 where the given keyframes there lie on one spot."""
    order = sorted(set(given) & set(placed))
    given_centres = np.array([given[k][:3, 3] for k in order], np.float64).reshape(-1, 3)
    placed_centres = np.array([placed[k][:3, 3] for k in order], np.float64).reshape(-1, 3)
    scales = {}
    for i, k in enumerate(order):
        lo, hi = max(0, i - window), min(len(order), i + window + 1)
        before = _pair_distances(given_centres[lo:hi])
        after = _pair_distances(placed_centres[lo:hi])
        scales[k] = after / before if before > 0 else 1.0
    return scales


def scaled_moves(given: Mapping[int, np.ndarray], placed: Mapping[int, np.ndarray],
                 window: int = SCALE_WINDOW) -> dict[int, np.ndarray]:
    """By keyframe index, the similarity taking each given (handed-out, rigid) pose to its placed rigid pose with its
    part of the map scaled by `local_scales` about the camera."""
    scales = local_scales(given, placed, window)
    if scales:
        values = np.array(list(scales.values()))
        log.info("final adjustment: %d keyframes' local scales %.3f (5 %%) %.3f (median) %.3f (95 %%)", len(values),
                 *np.percentile(values, [5, 50, 95]))
    moves = {}
    for k, scale in scales.items():
        target = np.array(placed[k], np.float64)
        target[:3, :3] *= scale
        moves[k] = target @ np.linalg.inv(np.asarray(given[k], np.float64))
    return moves


def _pair_distances(centres: np.ndarray) -> float:
    """The sum of the distances between every pair of `centres` [N, 3]."""
    if len(centres) < 2:
        return 0.0
    differences = centres[:, None, :] - centres[None, :, :]
    return float(np.linalg.norm(differences, axis=-1).sum() / 2)
