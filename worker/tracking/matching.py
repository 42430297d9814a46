"""Binary descriptor matching: ratio-test matching between two sets, and guided matching around projections."""

from __future__ import annotations

import cv2
import numpy as np

from worker.loop.vocabulary import hamming

from .features import Features

_MATCHER = cv2.BFMatcher(cv2.NORM_HAMMING)
_NONE = np.zeros(0, np.int64)


def unique_by_distance(ia: np.ndarray, ib: np.ndarray, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep, for every ib, only its closest match (ties: the first)."""
    order = np.argsort(distance, kind="stable")
    _, first = np.unique(ib[order], return_index=True)
    keep = np.sort(order[first])
    return ia[keep], ib[keep]


def ratio_matches(a: np.ndarray, b: np.ndarray, ratio: float, max_distance: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of one-to-one matches from descriptors a [N, 32] to b [M, 32] passing Lowe's ratio test."""
    if len(a) < 1 or len(b) < 2:
        return _NONE, _NONE
    pairs = _MATCHER.knnMatch(a, b, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < ratio * m[1].distance
            and m[0].distance <= max_distance]
    if not good:
        return _NONE, _NONE
    ia = np.array([m.queryIdx for m in good], np.int64)
    ib = np.array([m.trainIdx for m in good], np.int64)
    return unique_by_distance(ia, ib, np.array([m.distance for m in good]))


def match_by_projection(uv: np.ndarray, descriptors: np.ndarray, radius: np.ndarray, features: Features,
                        max_distance: int, ratio: float) -> np.ndarray:
    """For each projected point (uv [M, 2], descriptor [M, 32], search radius [M] pixels) the index of the
    keypoint it matches in `features`, or -1; one keypoint serves one point at the most."""
    out = np.full(len(uv), -1, np.int64)
    if len(uv) == 0 or len(features) == 0:
        return out
    kp = features.keypoints.astype(np.float32)
    d2 = ((uv[:, None, :].astype(np.float32) - kp[None]) ** 2).sum(-1)
    pi, ki = np.nonzero(d2 <= (radius.astype(np.float32) ** 2)[:, None])
    if len(pi) == 0:
        return out
    dist = hamming(descriptors[pi], features.descriptors[ki])
    order = np.lexsort((dist, pi))
    pi, ki, dist = pi[order], ki[order], dist[order]
    first = np.ones(len(pi), bool)
    first[1:] = pi[1:] != pi[:-1]
    best = np.flatnonzero(first)
    has_second = (best + 1 < len(pi)) & ~np.append(first, True)[best + 1]
    second = np.where(has_second, dist[np.minimum(best + 1, len(pi) - 1)], 256)
    ok = (dist[best] <= max_distance) & (dist[best] < ratio * second)
    best = best[ok]
    pts, kps = unique_by_distance(pi[best], ki[best], dist[best])
    out[pts] = kps
    return out
