"""The scale s of a camera-to-world similarity [sR | t; 0 1], sent beside every pose so clients need not derive it
(R = the 3x3 block / s is a rotation; with monocular input s != 1 in general)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def similarity_scale(pose: Sequence[float] | np.ndarray) -> float:
    """s = cbrt(|det(3x3 block)|) of a 4x4 pose (or its 16 row-major floats)."""
    block = np.asarray(pose, dtype=np.float64).reshape(4, 4)[:3, :3]
    return float(np.cbrt(abs(np.linalg.det(block))))
