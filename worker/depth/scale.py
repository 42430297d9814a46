"""Bring another depth map (the learned model's) to the scale of the confident multi-view depth."""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def confident_scale(other_depth: np.ndarray, mvs_depth: np.ndarray, confidence: np.ndarray,
                    min_confidence: float = 0.5, min_pixels: int = 100) -> float | None:
    """Median of mvs_depth / other_depth over pixels both have (finite, > 0) with confidence >= min_confidence;
    None (with a warning) when fewer than `min_pixels` such pixels exist."""
    other, mvs = np.asarray(other_depth, np.float64), np.asarray(mvs_depth, np.float64)
    if other.shape != mvs.shape or mvs.shape != np.shape(confidence):
        raise ValueError(f"shapes differ: other {other.shape}, mvs {mvs.shape}, confidence {np.shape(confidence)}")
    mask = (np.asarray(confidence) >= min_confidence) & np.isfinite(other) & np.isfinite(mvs) & (other > 0) & (mvs > 0)
    if int(mask.sum()) < min_pixels:
        log.warning("confident_scale: %d confident pixels (< %d); no scale", int(mask.sum()), min_pixels)
        return None
    return float(np.median(mvs[mask] / other[mask]))


def scale_to_confident(other_depth: np.ndarray, mvs_depth: np.ndarray, confidence: np.ndarray,
                       min_confidence: float = 0.5, min_pixels: int = 100) -> np.ndarray:
    """other_depth (float32) times `confident_scale`; returned unscaled when no scale can be measured."""
    scale = confident_scale(other_depth, mvs_depth, confidence, min_confidence, min_pixels)
    other = np.asarray(other_depth, dtype=np.float32)
    return other.copy() if scale is None else (other * np.float32(scale)).astype(np.float32)
