"""Descriptor matching between two photos: nearest neighbours both ways with Lowe's ratio test."""

from __future__ import annotations

import numpy as np

from .features import PhotoFeatures


def _nearest_two(similarity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row: the best column and the distances of the best and second best (unit vectors: d^2 = 2 - 2 s)."""
    if similarity.shape[1] < 2:
        best = np.argmax(similarity, axis=1)
        return best, np.sqrt(np.maximum(2 - 2 * similarity.max(1), 0)), np.full(len(similarity), np.inf)
    top = np.argpartition(-similarity, 1, axis=1)[:, :2]
    values = np.take_along_axis(similarity, top, axis=1)
    order = np.argsort(-values, axis=1)
    top, values = np.take_along_axis(top, order, axis=1), np.take_along_axis(values, order, axis=1)
    distance = np.sqrt(np.maximum(2 - 2 * values, 0))
    return top[:, 0], distance[:, 0], distance[:, 1]


def mutual_matches(a: PhotoFeatures, b: PhotoFeatures, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of the features that are each other's nearest neighbour and pass the ratio test both ways."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    similarity = a.descriptors @ b.descriptors.T
    best_ab, d1_ab, d2_ab = _nearest_two(similarity)
    best_ba, d1_ba, d2_ba = _nearest_two(similarity.T)
    ia = np.arange(len(a))
    keep = (best_ba[best_ab] == ia) & (d1_ab < ratio * d2_ab) & (d1_ba[best_ab] < ratio * d2_ba[best_ab])
    return ia[keep], best_ab[keep]
