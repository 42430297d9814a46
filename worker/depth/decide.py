"""From aggregated costs to depth and confidence (the per-pixel terms come from the kernels' `decide_terms`)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import MultiViewDepthConfig


@dataclass
class DecisionTerms:
    """Per pixel: the best hypothesis refined by a parabola (index, float64), whether it is inside the range
    (interior, bool), uniqueness of the aggregated cost against its runner-up (float32 in [0, 1]), the matching
    cost's margin below any hypothesis more than two away (float32 >= 0), the photometric score 1 - fused cost at
    the best (float32 in [0, 1]) and the number of views that agree (support, int16)."""

    index: np.ndarray
    interior: np.ndarray
    uniqueness: np.ndarray
    margin: np.ndarray
    photometric: np.ndarray
    support: np.ndarray


@dataclass
class Decision:
    """Per pixel: refined inverse depth, confidence in [0, 1] (0 where a check fails), agreeing views, and ok:
    the pixels that passed every check."""

    inv_depth: np.ndarray  # float64 [H, W]
    confidence: np.ndarray  # float32 [H, W]
    support: np.ndarray  # int16 [H, W]
    ok: np.ndarray  # bool [H, W]


def near_side_of_edges(inv_depth: np.ndarray, radius: int, jump: float) -> np.ndarray:
    """bool [H, W]: pixels with a point farther by more than `jump` (relative, in inverse depth) within `radius`.

    Window costs fatten foreground objects: the background pixels up to a window radius beyond an occluding edge
    take the foreground's depth, so the near side of every depth edge is unreliable for `radius` pixels.
    """
    size = 2 * radius + 1
    farthest = cv2.erode(inv_depth.astype(np.float32), np.ones((size, size), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return inv_depth - farthest > jump * inv_depth


def small_speckles(index: np.ndarray, ok: np.ndarray, max_size: int, max_step: float) -> np.ndarray:
    """bool [H, W]: kept pixels in connected regions (neighbours within `max_step` hypotheses) of fewer than
    `max_size` pixels: isolated blobs are mostly wrong matches."""
    if max_size <= 0:
        return np.zeros(index.shape, dtype=bool)
    fixed = np.where(ok, np.round(index * 16.0), -32000).astype(np.int16)
    filtered = fixed.copy()
    cv2.filterSpeckles(filtered, -32000, max_size, int(round(max_step * 16)))
    return ok & (filtered != fixed)


def decide(terms: DecisionTerms, inv_depths: np.ndarray, config: MultiViewDepthConfig) -> Decision:
    """Inverse depth at the refined index (hypotheses are uniform in inverse depth); confidence = photometric score
    x distinctiveness (the lower of uniqueness / `uniqueness_full` and margin / `margin_full`, at most 1), zeroed
    at the range ends, where fewer than `min_views` agree, on the
    near side of depth edges and in small isolated regions."""
    step = (inv_depths[-1] - inv_depths[0]) / max(len(inv_depths) - 1, 1)
    inv_depth = inv_depths[0] + terms.index * step
    distinct = np.clip(np.minimum(terms.uniqueness / config.uniqueness_full, terms.margin / config.margin_full), 0, 1)
    confidence = terms.photometric * distinct
    ok = terms.interior & (terms.support >= config.min_views) & (inv_depth > 0)
    ok &= confidence >= config.min_confidence
    if config.edge_jump > 0:
        ok &= ~near_side_of_edges(inv_depth, config.window_radius, config.edge_jump)
    ok &= ~small_speckles(terms.index, ok, config.speckle_size, config.speckle_step)
    return Decision(inv_depth=inv_depth, confidence=np.where(ok, confidence, 0.0).astype(np.float32),
                    support=terms.support, ok=ok)
