"""Validation of client-supplied camera-to-world poses `[s R | t; 0 0 0 1]` (a similarity: uniform scale s > 0).

Refused: non-finite values, a last row other than (0, 0, 0, 1), shear or non-uniform scale (R^T R off the
identity), reflections (det < 0), a degenerate or absurd scale, and absurdly large translations. A refused pose
would otherwise poison the map (a shear inflated it 3.5x) or the trajectory (an all-zero pose gave NaN).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PoseLimits:
    """`tolerance`: largest |R^T R - I| entry and |det R - 1| (float32 phones stay near 1e-6); `max_translation`:
    metres from the origin; `min_scale`/`max_scale`: the similarity's uniform scale s."""

    tolerance: float = 1e-3
    max_translation: float = 1e4
    min_scale: float = 1e-3
    max_scale: float = 1e3


DEFAULT_LIMITS = PoseLimits()


def pose_problem(values: Sequence[float], limits: PoseLimits = DEFAULT_LIMITS) -> str | None:
    """Why `values` (16 floats, row-major) is not an acceptable camera-to-world pose; None when it is."""
    if len(values) != 16:
        return f"pose must have 16 values (4x4 row-major), got {len(values)}"
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
        return "pose must be 16 finite numbers"
    m = np.asarray(values, dtype=np.float64).reshape(4, 4)
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > limits.tolerance:
        return f"pose's last row must be 0 0 0 1, got {m[3].tolist()}"
    a = m[:3, :3]
    det = float(np.linalg.det(a))
    if not det > 0:
        return (f"pose's rotation block has determinant {det:.3g}: a reflection or a degenerate matrix, not a "
                "rotation")
    scale = det ** (1.0 / 3.0)
    if not limits.min_scale <= scale <= limits.max_scale:
        return f"pose's scale {scale:.3g} is outside [{limits.min_scale:g}, {limits.max_scale:g}]"
    rot = a / scale
    off = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if off > limits.tolerance:
        return (f"pose is not rigid: R^T R differs from the identity by {off:.3g} (shear or non-uniform scale; "
                f"tolerance {limits.tolerance:g})")
    translation = math.hypot(*m[:3, 3].tolist())
    if translation > limits.max_translation:
        return f"pose's translation of {translation:.3g} m exceeds the limit of {limits.max_translation:g} m"
    return None
