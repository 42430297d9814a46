"""Small motion helpers shared by the pose sources: the constant-velocity guess and the size of a motion."""

from __future__ import annotations

import math

import numpy as np


def motion_model_pose(previous: np.ndarray | None, last: np.ndarray) -> np.ndarray:
    """The next c2w pose under constant velocity: last * (previous^-1 * last); `last` when there is no history."""
    if previous is None:
        return np.asarray(last, np.float64).copy()
    return last @ (np.linalg.inv(previous) @ last)


def relative_motion(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation, rotation in degrees) between two rigid c2w poses."""
    rel = np.linalg.inv(a) @ b
    cos = (np.trace(rel[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(rel[:3, 3])), math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))
