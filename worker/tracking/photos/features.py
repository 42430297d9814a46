"""SIFT keypoints with RootSIFT descriptors (L1-normalised square roots: Euclidean distance becomes the Hellinger
kernel, which matches photos taken from far apart better than plain SIFT)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class PhotoFeatures:
    """Keypoints [N, 2] (pixels, float64) and unit-length RootSIFT descriptors [N, 128] (float32)."""

    keypoints: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def extract_features(gray: np.ndarray, max_features: int) -> PhotoFeatures:
    """The SIFT features of a grey uint8 image, strongest first."""
    keypoints, descriptors = cv2.SIFT_create(nfeatures=max_features).detectAndCompute(gray, None)
    if descriptors is None or not keypoints:
        return PhotoFeatures(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    root = np.sqrt(descriptors / np.maximum(descriptors.sum(1, keepdims=True), 1e-9))
    root /= np.maximum(np.linalg.norm(root, axis=1, keepdims=True), 1e-9)
    uv = np.array([k.pt for k in keypoints], np.float64)
    return PhotoFeatures(uv, root.astype(np.float32))
