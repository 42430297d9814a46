"""The scene's length unit: lengths that must follow the scene, whatever the units of the poses.

Poses come in metres (ARKit, ARCore, a LiDAR phone: an object 0.3 m away, a drone 100 m above a field), in a
monocular odometry's own units (its first keyframe's median depth is 1) or in whatever a dataset chose. A length
that means "small against the scene" (the odometry noise of a pose graph's edges, how far two depth maps may be
apart and still fit) is a multiple of the scene's length unit, the median depth of the first keyframe whose depth
is known (sensor depth, multi-view stereo, an odometry's triangulated points), never a number of metres: the same
images mapped in centimetres, metres or kilometres give the same map.
"""

from __future__ import annotations

import math

import numpy as np

MIN_DEPTHS = 20  # valid depths needed for a median


def median_depth(depth: np.ndarray | None) -> float | None:
    """The median of a z-depth map's valid values (0, negative or non-finite = unknown), on every second pixel;
    None with fewer than MIN_DEPTHS of them."""
    if depth is None:
        return None
    values = np.asarray(depth)[::2, ::2]
    values = values[np.isfinite(values) & (values > 0)]
    return float(np.median(values)) if values.size >= MIN_DEPTHS else None


def valid_unit(unit: float | None) -> float | None:
    """`unit` when it can be a length unit (finite, > 0), else None."""
    if unit is None or not math.isfinite(unit) or unit <= 0:
        return None
    return float(unit)
