"""Image sharpness: the variance of the Laplacian, the measure that falls with motion blur (and with texture)."""

from __future__ import annotations

import cv2
import numpy as np

SHARPNESS_SIDE = 160  # the longer side (pixels) at which sharpness is measured


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (RGB uint8 [H, W, 3], or grey [H, W] of any scale) reduced to
    about SHARPNESS_SIDE pixels on its longer side: higher is sharper. Compare values of images of one scale."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    h, w = grey.shape
    factor = max(1, round(max(h, w) / SHARPNESS_SIDE))
    if factor > 1:
        grey = cv2.resize(grey, (max(1, w // factor), max(1, h // factor)), interpolation=cv2.INTER_AREA)
    _, std = cv2.meanStdDev(cv2.Laplacian(grey, cv2.CV_32F))
    return float(std[0, 0]) ** 2
