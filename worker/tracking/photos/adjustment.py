"""Bundle adjustment of a reconstruction's photos and points (worker.tracking.bundle_adjustment), and the
observations it leaves as outliers dropped."""

from __future__ import annotations

import numpy as np

from ..bundle_adjustment import Observations, bundle_adjust, reprojection_chi2
from .reconstruction import Reconstruction


def window_around(m: Reconstruction, slot: int, size: int) -> np.ndarray:
    """Photo `slot` and the `size` - 1 photos sharing most points with it (those sharing any)."""
    shared = m.shared_points(slot)
    shared[slot] = -1
    return np.array([slot] + [int(s) for s in np.argsort(-shared)[: size - 1] if shared[s] > 0])


def adjust(m: Reconstruction, K: np.ndarray, free: np.ndarray, held: np.ndarray, iterations: int,
           chi2_px: float) -> bool:
    """Adjust the photos `free` (slots) and the points they see; `held` and every other photo seeing those points
    stay where they are (one photo at least: the gauge). Observations that still reproject worse than chi2_px
    (squared pixels) are dropped after. Returns whether the solve ran."""
    obs, index = m.observations_of(np.union1d(free, held))
    if len(index) == 0:
        return False
    slots = np.unique(obs.keyframe)
    fixed = ~np.isin(slots, free)
    if not fixed.any():
        fixed[0] = True
    local = Observations(np.searchsorted(slots, obs.keyframe), obs.point, obs.uv, obs.sigma)
    poses, points, ran = bundle_adjust(m.poses()[slots], fixed, m.points, local, K, iterations)
    if not ran:
        return False
    for k, s in enumerate(slots):
        m.photos[s].pose = poses[k]
    m.points = points
    chi2 = reprojection_chi2(poses, points, local, K)
    m.forget(index[~(chi2 < chi2_px)])
    return True
