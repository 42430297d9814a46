"""Real pinhole images seen through a lens: what a camera with intrinsics `camera` and the given distortion shows
of the scene an undistorted image (taken with the same K) shows. The oracle of the undistortion tests; built with
OpenCV's point undistortion, not with the remap maps under test."""

from __future__ import annotations

import cv2
import numpy as np

from worker.geometry import Intrinsics

# The TUM RGB-D "freiburg1" Kinect's published colour calibration (radial-tangential), and a wide-angle fisheye.
TUM_FR1 = {"model": "radtan", "k1": 0.262383, "k2": -0.953104, "p1": -0.005358, "p2": 0.002628, "k3": 1.163314}
FISHEYE = {"model": "fisheye", "k1": -0.013, "k2": 0.021, "k3": -0.011, "k4": 0.002}


def _matrix(camera: Intrinsics) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def distort(image: np.ndarray, camera: Intrinsics, distortion: dict, nearest: bool = False) -> np.ndarray:
    """`image` (a pinhole image with intrinsics `camera`) as the lens `distortion` with the same K would see it."""
    h, w = image.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    K = _matrix(camera)
    if distortion["model"] == "fisheye":
        d = np.array([distortion.get(k, 0.0) for k in ("k1", "k2", "k3", "k4")])
        ideal = cv2.fisheye.undistortPoints(pixels, K, d, P=K)
    else:
        d = np.array([distortion.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
        ideal = cv2.undistortPoints(pixels, K, d, P=K,
                                    criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6))
    map_x = ideal[:, 0, 0].reshape(h, w).astype(np.float32)
    map_y = ideal[:, 0, 1].reshape(h, w).astype(np.float32)
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)


def to_pinhole(image: np.ndarray, camera: Intrinsics, target: Intrinsics) -> np.ndarray:
    """A pinhole image with intrinsics `camera` as the pinhole camera `target` (same centre) sees it."""
    homography = _matrix(camera) @ np.linalg.inv(_matrix(target))
    return cv2.warpPerspective(image, homography, (target.width, target.height),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
