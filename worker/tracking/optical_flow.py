"""Sub-pixel point tracking between consecutive frames: pyramidal Lucas-Kanade optical flow with a forward-backward
check, and corner detection that fills the image where no track is (project pixel convention: centres at +0.5).
"""

from __future__ import annotations

import cv2
import numpy as np

_HALF = np.float32(0.5)  # OpenCV puts pixel centres at integers, this project at +0.5


def track_points(previous: np.ndarray, current: np.ndarray, uv: np.ndarray, guess: np.ndarray | None = None, *,
                 window: int = 21, levels: int = 3, max_fb_px: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """Positions [N, 2] in `current` of the pixels `uv` [N, 2] of `previous` (uint8 grey images) and the mask [N] of
    those tracked both ways: forward from `guess` (or uv), then back to within `max_fb_px` of where they started."""
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    start = (uv.astype(np.float32) - _HALF).reshape(-1, 1, 2)
    flags, forward = 0, None
    if guess is not None:
        forward, flags = (guess.astype(np.float32) - _HALF).reshape(-1, 1, 2).copy(), cv2.OPTFLOW_USE_INITIAL_FLOW
    forward, ok_f, _ = cv2.calcOpticalFlowPyrLK(previous, current, start, forward, winSize=(window, window),
                                                maxLevel=levels, criteria=criteria, flags=flags)
    # The backward pass starts from the original pixels, as the forward one from its guess: motions larger than the
    # pyramid reaches (or a repeated texture) would fail an unguided return. Tracks it lets pass wrongly are
    # outliers of the pose (map points) or of the triangulation (candidates).
    backward, ok_b, _ = cv2.calcOpticalFlowPyrLK(current, previous, forward, start.copy(), winSize=(window, window),
                                                 maxLevel=levels, criteria=criteria,
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    forward, backward = forward.reshape(-1, 2), backward.reshape(-1, 2)
    h, w = current.shape
    fb = np.linalg.norm(backward - start.reshape(-1, 2), axis=1)
    inside = (forward[:, 0] >= 0) & (forward[:, 0] <= w - 1) & (forward[:, 1] >= 0) & (forward[:, 1] <= h - 1)
    ok = ok_f.ravel().astype(bool) & ok_b.ravel().astype(bool) & (fb < max_fb_px) & inside
    ok &= np.isfinite(forward).all(axis=1)
    return forward + _HALF, ok


def predicted_pixels(uv: np.ndarray, points: np.ndarray, mapped: np.ndarray, previous: np.ndarray,
                     predicted: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Where pixels uv [N, 2] of a camera at `previous` should land at `predicted` (c2w poses): those with a world
    point (mask `mapped` [N]; points [n, 3] in that order) by projection, the others as points at infinity (the
    rotation alone)."""
    guess = uv.astype(np.float64).copy()
    rel = np.linalg.inv(predicted) @ previous  # previous camera -> predicted camera
    H = K @ rel[:3, :3] @ np.linalg.inv(K)
    ray = np.concatenate([guess, np.ones((len(guess), 1))], axis=1) @ H.T
    ahead = ray[:, 2] > 1e-6
    guess[ahead] = ray[ahead, :2] / ray[ahead, 2:]
    pc = (points - predicted[:3, 3]) @ predicted[:3, :3]
    front = pc[:, 2] > 1e-6
    rows = np.flatnonzero(mapped)[front]
    guess[rows, 0] = K[0, 0] * pc[front, 0] / pc[front, 2] + K[0, 2]
    guess[rows, 1] = K[1, 1] * pc[front, 1] / pc[front, 2] + K[1, 2]
    return guess


def refine_points(template: np.ndarray, current: np.ndarray, uv: np.ndarray, guess: np.ndarray, *,
                  window: int = 21, max_shift_px: float = 1.0) -> np.ndarray:
    """`guess` [N, 2] moved to where the pixels `uv` [N, 2] of `template` (an older frame) match `current` best,
    where that is found within `max_shift_px` of the guess (elsewhere the guess stays). Following a point from one
    template rather than from frame to frame keeps its small errors from adding up."""
    if len(uv) == 0:
        return guess.astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    start = (uv.astype(np.float32) - _HALF).reshape(-1, 1, 2)
    refined = (guess.astype(np.float32) - _HALF).reshape(-1, 1, 2).copy()
    refined, ok, _ = cv2.calcOpticalFlowPyrLK(template, current, start, refined, winSize=(window, window), maxLevel=1,
                                              criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    refined = refined.reshape(-1, 2) + _HALF
    near = ok.ravel().astype(bool) & (np.linalg.norm(refined - guess, axis=1) <= max_shift_px)
    near &= np.isfinite(refined).all(axis=1)
    return np.where(near[:, None], refined, guess).astype(np.float32)


def detect_corners(gray: np.ndarray, existing: np.ndarray, count: int, min_distance: float,
                   quality: float = 0.01, border: int = 8) -> np.ndarray:
    """Up to `count` new Shi-Tomasi corners [n, 2] at least `min_distance` pixels from each other and from the
    `existing` points [m, 2], away from the image border."""
    if count <= 0:
        return np.zeros((0, 2), np.float32)
    h, w = gray.shape
    mask = np.zeros((h, w), np.uint8)
    mask[border:h - border, border:w - border] = 255
    radius = max(1, int(round(min_distance)))
    for x, y in np.rint(existing - _HALF).astype(np.int32):
        cv2.circle(mask, (int(x), int(y)), radius, 0, -1)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=count, qualityLevel=quality, minDistance=min_distance,
                                      mask=mask, blockSize=5)
    if corners is None:
        return np.zeros((0, 2), np.float32)
    # Sub-pixel corners start the flow where the image is best conditioned (they may move by a pixel or two).
    corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (3, 3), (-1, -1),
                               (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03))
    return corners.reshape(-1, 2) + _HALF
