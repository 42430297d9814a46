"""Focal length of an uncalibrated camera from the first frames' epipolar geometry.

With the principal point at the image centre and square pixels, E = K^T F K is an essential matrix only for the
right focal length f, and an essential matrix has two equal singular values. The estimate minimises the summed
Mendonca-Cipolla cost (s1 - s2) / (s1 + s2) over several frame pairs on a log grid of f; it is trusted only when
the minimum stands out and lies inside the grid, else the guess `focal_guess * max(W, H)` stays.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from worker.geometry import Intrinsics

from .features import Features
from .matching import ratio_matches
from .vo_config import VisualOdometryConfig

_GRID = np.exp(np.linspace(np.log(0.3), np.log(3.0), 161))  # focal / max(W, H)


def essential_cost(F: np.ndarray, focal: float, cx: float, cy: float) -> float:
    """(s1 - s2) / (s1 + s2) of K^T F K: 0 for a true essential matrix."""
    K = np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    s = np.linalg.svd(K.T @ F @ K, compute_uv=False)
    return float((s[0] - s[1]) / max(s[0] + s[1], 1e-300))


def focal_costs(fundamentals: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """Summed cost over the pairs for each focal of the grid (focal = grid * max(W, H))."""
    scale = max(width, height)
    return np.array([sum(essential_cost(F, g * scale, width / 2, height / 2) for F in fundamentals) for g in _GRID])


class FocalEstimator:
    """Collects fundamental matrices of the frames before initialisation and estimates the focal from them."""

    def __init__(self, config: VisualOdometryConfig, max_pairs: int = 12) -> None:
        self.config = config
        self.max_pairs = max_pairs
        self.fundamentals: list[np.ndarray] = []
        self.ratio: float | None = None  # estimated focal / max(W, H)
        self.frozen = False

    def intrinsics(self, width: int, height: int) -> Intrinsics:
        """The current estimate (or the guess) as intrinsics with the principal point at the image centre."""
        f = (self.ratio or self.config.focal_guess) * max(width, height)
        return Intrinsics(f, f, width / 2, height / 2, width, height)

    def observe(self, a: Features, b: Features, camera: Intrinsics) -> None:
        """Add the pair (a, b) when its epipolar geometry is well determined, and re-estimate."""
        if self.frozen or not self.config.self_calibrate:
            return
        ia, ib = ratio_matches(a.descriptors, b.descriptors, self.config.match_ratio, self.config.max_hamming)
        self.observe_matches(a.keypoints[ia], b.keypoints[ib], camera)

    def observe_matches(self, pa: np.ndarray, pb: np.ndarray, camera: Intrinsics) -> None:
        """Add the pair of matched pixels pa, pb [N, 2] when its epipolar geometry is well determined, and
        re-estimate."""
        if self.frozen or not self.config.self_calibrate or len(pa) < self.config.init_min_matches:
            return
        pa, pb = pa.astype(np.float64), pb.astype(np.float64)
        # Motion that a homography explains (rotation, a plane, too little baseline) fixes no focal length.
        if np.median(np.linalg.norm(pa - pb, axis=1)) < 0.02 * max(camera.width, camera.height):
            return
        F, f_mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.999)
        H, h_mask = cv2.findHomography(pa, pb, cv2.RANSAC, 2.0)
        if F is None or F.shape != (3, 3) or f_mask is None:
            return
        if H is not None and h_mask is not None and h_mask.sum() > 0.8 * f_mask.sum():
            return
        self.fundamentals = (self.fundamentals + [F / np.linalg.norm(F)])[-self.max_pairs:]
        self._estimate(camera.width, camera.height)

    def _estimate(self, width: int, height: int) -> None:
        if len(self.fundamentals) < 3:
            return
        costs = focal_costs(self.fundamentals, width, height)
        best = int(np.argmin(costs))
        if 0 < best < len(_GRID) - 1 and costs[best] < 0.5 * np.median(costs):
            self.ratio = float(_GRID[best])

    def freeze(self) -> None:
        """The map is built with the current focal: keep it."""
        self.frozen = True

    def state_dict(self) -> dict[str, Any]:
        return {"fundamentals": [F for F in self.fundamentals], "ratio": -1.0 if self.ratio is None else self.ratio,
                "frozen": self.frozen}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.fundamentals = [np.asarray(F, np.float64).reshape(3, 3) for F in state["fundamentals"]]
        self.ratio = None if float(state["ratio"]) < 0 else float(state["ratio"])
        self.frozen = bool(state["frozen"])
