"""Whether a pose-graph solution may be applied: a solve that diverged (gtsam's damped batch solve after iSAM2
gave up can end there) must not move the trajectory and the map.

Measured where it happened: TUM fr1/xyz RGB-D streamed live, iSAM2 failed on an indeterminate system several times
and a batch solve gave a keyframe a similarity of scale 1e8, which the trajectory took and the map then refused
(the session failed). The bounds below are what no real correction does, not tuned figures: metric poses and depth
leave nothing to change a scale, and a monocular map's scale does not change tenfold at one loop.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

# Largest factor a solve may change a keyframe's scale by: metric input (given poses or depth), else monocular.
METRIC_SCALE_CHANGE = 1.25
MONOCULAR_SCALE_CHANGE = 10.0


def implausible_correction(before: Mapping[int, np.ndarray], after: Mapping[int, np.ndarray], metric: bool
                           ) -> str | None:
    """Why the solved poses `after` must not replace `before` (keyframe -> 4x4 similarity), or None when they may:
    a pose that is not finite or not a proper similarity, or a keyframe's scale changed by more than the bound."""
    bound = METRIC_SCALE_CHANGE if metric else MONOCULAR_SCALE_CHANGE
    for key, pose in after.items():
        pose = np.asarray(pose, np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            return f"keyframe {key} solved to a pose that is not finite"
        det = np.linalg.det(pose[:3, :3])
        if det <= 0:
            return f"keyframe {key} solved to a pose that is not a proper similarity"
        if key in before:
            old = np.linalg.det(np.asarray(before[key], np.float64)[:3, :3])
            ratio = np.cbrt(det / old) if old > 0 else np.inf
            if not 1.0 / bound <= ratio <= bound:
                return f"keyframe {key}'s scale changed {ratio:.3g} times in one solve"
    return None
