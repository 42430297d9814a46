"""Undistortion: a distorted camera's images brought, once, to a pinhole camera of the same size.

The pinhole camera keeps only pixels that lie inside the photo (OpenCV's optimal new camera matrix with alpha 0;
for a fisheye, its new camera matrix with balance 0), so an undistorted frame has no black border for the map to
learn. The maps are computed once per camera and size (`undistortion` caches them): a frame then costs one remap.
Colour is interpolated bilinearly; depth registered to the colour image takes its nearest sample (averaging would
mix depths with holes and across edges). The wire form of a lens is `protocol.lens`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from protocol.lens import FISHEYE, RADTAN, coefficients, is_identity

from .camera import Intrinsics


@dataclass(frozen=True)
class Lens:
    """A lens distortion: `model` radtan (k1, k2, p1, p2, k3) or fisheye (k1, k2, k3, k4), in OpenCV's order."""

    model: str
    coefficients: tuple[float, ...]

    @classmethod
    def from_wire(cls, distortion: dict[str, Any] | None) -> Lens | None:
        """The lens of a checked wire distortion (`protocol.lens`); None when it changes nothing."""
        if is_identity(distortion):
            return None
        return cls(*coefficients(distortion))

    @property
    def array(self) -> np.ndarray:
        return np.asarray(self.coefficients, np.float64)


def matrix(camera: Intrinsics) -> np.ndarray:
    """The 3x3 camera matrix K."""
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def _from_matrix(K: np.ndarray, width: int, height: int) -> Intrinsics:
    return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)


def undistorted_camera(camera: Intrinsics, lens: Lens) -> Intrinsics:
    """The pinhole camera of `camera`'s undistorted images: same size, every pixel inside the photo."""
    size = (camera.width, camera.height)
    if lens.model == FISHEYE:
        K = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(matrix(camera), lens.array, size, np.eye(3),
                                                                    balance=0.0)
    elif lens.model == RADTAN:
        K, _ = cv2.getOptimalNewCameraMatrix(matrix(camera), lens.array, size, 0.0, size)
    else:
        raise ValueError(f"unknown lens model {lens.model!r}")
    return _from_matrix(K, camera.width, camera.height)


class Undistortion:
    """Images of a distorted camera (`distorted`, at their size) remapped to the pinhole camera `pinhole`."""

    def __init__(self, distorted: Intrinsics, lens: Lens, pinhole: Intrinsics) -> None:
        if (distorted.width, distorted.height) != (pinhole.width, pinhole.height):
            raise ValueError("the distorted and the pinhole camera must be of one size")
        self.pinhole = pinhole
        size = (distorted.width, distorted.height)
        if lens.model == FISHEYE:
            self._maps = cv2.fisheye.initUndistortRectifyMap(matrix(distorted), lens.array, np.eye(3),
                                                             matrix(pinhole), size, cv2.CV_16SC2)
        else:
            self._maps = cv2.initUndistortRectifyMap(matrix(distorted), lens.array, None, matrix(pinhole), size,
                                                     cv2.CV_16SC2)

    def image(self, image: np.ndarray) -> np.ndarray:
        """A colour (or grey) image, bilinear; what falls outside the photo is edge-replicated (alpha 0: none)."""
        return cv2.remap(image, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A depth image registered to the distorted colour image, nearest sample (0 outside)."""
        return cv2.remap(depth, *self._maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


@lru_cache(maxsize=16)
def undistortion(distorted: Intrinsics, lens: Lens, pinhole: Intrinsics) -> Undistortion:
    """The (cached) undistortion of one camera at one size: sessions stream one camera at one size."""
    return Undistortion(distorted, lens, pinhole)
