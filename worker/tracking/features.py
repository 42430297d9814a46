"""ORB keypoints spread over the image, in the project's pixel convention (pixel centres at +0.5)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .vo_config import VisualOdometryConfig


@dataclass
class Features:
    """Keypoints [N, 2] (x, y pixels), binary descriptors [N, 32] uint8 and pyramid octaves [N] of one frame."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    octaves: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)

    @classmethod
    def empty(cls) -> Features:
        return cls(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.int32))

    def subset(self, index: np.ndarray) -> Features:
        return Features(self.keypoints[index], self.descriptors[index], self.octaves[index])

    def to_state(self) -> dict[str, np.ndarray]:
        return {"keypoints": self.keypoints, "descriptors": self.descriptors, "octaves": self.octaves}

    @classmethod
    def from_state(cls, state: dict) -> Features:
        return cls(np.asarray(state["keypoints"], np.float32).reshape(-1, 2),
                   np.asarray(state["descriptors"], np.uint8).reshape(-1, 32),
                   np.asarray(state["octaves"], np.int32).reshape(-1))


class OrbExtractor:
    """cv2 ORB over a pyramid, then at most a fair share of the strongest corners per grid cell."""

    def __init__(self, config: VisualOdometryConfig) -> None:
        self.config = config
        self._orbs: dict[int, cv2.ORB] = {}
        # Local contrast equalisation lets dim or low-contrast surfaces yield corners at the same FAST threshold.
        self._clahe = cv2.createCLAHE(clipLimit=config.clahe_clip, tileGridSize=(4, 4)) if config.clahe_clip else None

    def level_sigmas(self, octaves: np.ndarray) -> np.ndarray:
        """Pixel noise (sigma) of keypoints detected at `octaves`: one pixel at the pyramid's level."""
        return self.config.scale_factor ** np.asarray(octaves, np.float64)

    def _orb(self, height: int, width: int) -> cv2.ORB:
        # The 31-pixel patch wastes much of a small image's border; shrink it below VGA.
        patch = 31 if min(height, width) >= 400 else 19
        if patch not in self._orbs:
            c = self.config
            self._orbs[patch] = cv2.ORB_create(
                nfeatures=3 * c.n_features, scaleFactor=c.scale_factor, nlevels=c.n_levels, edgeThreshold=patch,
                patchSize=patch, fastThreshold=c.fast_threshold)
        return self._orbs[patch]

    def extract(self, gray: np.ndarray) -> Features:
        """Features of a uint8 grey image [H, W]."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"extract takes a uint8 grey image [H, W], got {gray.dtype} {gray.shape}")
        orb = self._orb(*gray.shape)
        if self._clahe is not None:
            gray = self._clahe.apply(gray)
        keypoints = orb.detect(gray, None)
        if not keypoints:
            return Features.empty()
        keypoints = [keypoints[i] for i in self._spread(keypoints, gray.shape)]
        keypoints, descriptors = orb.compute(gray, keypoints)
        if descriptors is None or not keypoints:
            return Features.empty()
        xy = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2) + 0.5
        octaves = np.array([k.octave for k in keypoints], np.int32)
        return Features(xy, descriptors, octaves)

    def _spread(self, keypoints: list[cv2.KeyPoint], shape: tuple[int, int]) -> np.ndarray:
        """Indices of the keypoints kept: the strongest first in each cell, round-robin over cells."""
        cell = self.config.grid_cell
        xy = np.array([k.pt for k in keypoints], np.float32)
        response = np.array([k.response for k in keypoints], np.float32)
        cols = int(np.ceil(shape[1] / cell))
        cell_id = (xy[:, 1] // cell).astype(np.int64) * cols + (xy[:, 0] // cell).astype(np.int64)
        order = np.lexsort((-response, cell_id))  # by cell, strongest first within a cell
        sorted_cells = cell_id[order]
        first = np.searchsorted(sorted_cells, sorted_cells, side="left")
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order)) - first
        # Round-robin: every cell's best, then every cell's second best, ...; ties by response.
        keep = np.lexsort((-response, rank))[: self.config.n_features]
        return keep
