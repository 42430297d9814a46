"""Device poses checked against tracking: a frame's device motion that disagrees with the tracked motion is a jump.

ARKit/ARCore relocalise with a jump, a dataset's pose stream may glitch: over one frame the device's relative motion
then differs from what the images show. Both motions are relative (previous^-1 @ current), so the comparison does not
depend on the world frames of the two trajectories.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MotionDisagreement:
    """How far a device motion is from the tracked one: translation (pose units) and rotation (degrees)."""

    translation: float
    rotation_deg: float

    def exceeds(self, translation: float, rotation_deg: float) -> bool:
        return self.translation > translation or self.rotation_deg > rotation_deg


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^-1 @ b for c2w poses: the motion from a to b in a's camera frame."""
    return np.linalg.inv(np.asarray(a, np.float64)) @ np.asarray(b, np.float64)


def disagreement(device_motion: np.ndarray, tracked_motion: np.ndarray) -> MotionDisagreement:
    """The difference of two relative motions: |t_d - t_t| and the angle of R_d^T R_t."""
    d, t = np.asarray(device_motion, np.float64), np.asarray(tracked_motion, np.float64)
    cos = (np.trace(d[:3, :3].T @ t[:3, :3]) - 1.0) / 2.0
    return MotionDisagreement(float(np.linalg.norm(d[:3, 3] - t[:3, 3])),
                              math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0)))))


def motion_size(motion: np.ndarray) -> MotionDisagreement:
    """A relative motion's own distance and angle (its disagreement with standing still)."""
    return disagreement(motion, np.eye(4))


def checked_device_pose(pose: np.ndarray | None, index: int) -> np.ndarray:
    """A frame's device pose as float64 4x4, refused with a clear message when missing, malformed or not finite."""
    if pose is None:
        raise ValueError(f"frame {index} has no pose, but this session runs in posed mode")
    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"frame {index}: the pose is not a finite 4x4 matrix")
    return pose
