"""A motion guess from features for dense alignment: ORB matches between a reference RGB-D frame and the current
image, the reference's depth at its keypoints, PnP + RANSAC. Dense alignment converges only from a guess near the
answer; this one does not depend on the motion model, so it rescues fast motion, a first step without velocity
history, and scenes whose geometry or texture repeats (a corridor, a street, a tiled floor)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MIN_INLIERS = 25


@dataclass
class KeypointSet:
    """ORB keypoints (pixel centres at +0.5) and descriptors of one image; `points` their camera-frame 3D points
    when the image has depth (z = 0 where unknown)."""

    pixels: np.ndarray  # float32 [N, 2]
    descriptors: np.ndarray  # uint8 [N, 32]
    points: np.ndarray | None = None


_orb = cv2.ORB_create(nfeatures=800, scaleFactor=1.2, nlevels=4, fastThreshold=10)
_matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)


def detect(grey_u8: np.ndarray, points: np.ndarray | None = None) -> KeypointSet:
    """Keypoints of a uint8 grey image; with `points` ([H, W, 3] camera-frame points), their 3D points."""
    keypoints, descriptors = _orb.detectAndCompute(grey_u8, None)
    if descriptors is None or not keypoints:
        return KeypointSet(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8),
                           None if points is None else np.zeros((0, 3), np.float32))
    pixels = np.array([k.pt for k in keypoints], np.float32) + 0.5
    xyz = None
    if points is not None:
        h, w = points.shape[:2]
        cols = np.clip(pixels[:, 0].astype(np.int64), 0, w - 1)
        rows = np.clip(pixels[:, 1].astype(np.int64), 0, h - 1)
        xyz = points[rows, cols]
    return KeypointSet(pixels, descriptors, xyz)


def pnp_seed(reference: KeypointSet, current: KeypointSet, K: np.ndarray) -> np.ndarray | None:
    """T_cur_ref (4x4) from matches of reference keypoints with depth to current keypoints, or None when too few
    matches agree."""
    if reference.points is None or len(reference.pixels) < MIN_INLIERS or len(current.pixels) < MIN_INLIERS:
        return None
    matches = _matcher.match(reference.descriptors, current.descriptors)
    if len(matches) < MIN_INLIERS:
        return None
    ri = np.array([m.queryIdx for m in matches])
    ci = np.array([m.trainIdx for m in matches])
    xyz = reference.points[ri].astype(np.float64)
    keep = xyz[:, 2] > 0
    if int(keep.sum()) < MIN_INLIERS:
        return None
    object_points = xyz[keep]
    image_points = current.pixels[ci][keep].astype(np.float64) - 0.5  # OpenCV: pixel centres at integers
    K_cv = np.asarray(K, np.float64).copy()
    K_cv[:2, 2] -= 0.5
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(object_points, image_points, K_cv, None, iterationsCount=200,
                                                 reprojectionError=2.0, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < MIN_INLIERS:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T if np.all(np.isfinite(T)) else None
