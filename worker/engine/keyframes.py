"""Keyframe selection from poses: the first frame, then every N frames or when the camera moved or turned enough
since the last keyframe (used in posed mode, where the poses come with the frames)."""

from __future__ import annotations

import math

import numpy as np
import torch

from worker.geometry import relative_transform, sim3_decompose, so3_log


class MotionKeyframeSelector:
    """Decides, frame by frame, whether a pose starts a new keyframe."""

    def __init__(self, every: int, translation: float, rotation_deg: float) -> None:
        self.every = every
        self.translation = translation
        self.rotation = math.radians(rotation_deg)
        self.last_pose: np.ndarray | None = None
        self.frames_since = 0

    def is_keyframe(self, pose: np.ndarray, force: bool = False) -> bool:
        """Whether `pose` (c2w 4x4) is a keyframe (always when `force`); updates the selector's state."""
        self.frames_since += 1
        if force or self.last_pose is None or self.frames_since >= self.every or self._moved(pose):
            self.last_pose = np.asarray(pose, np.float64).copy()
            self.frames_since = 0
            return True
        return False

    def _moved(self, pose: np.ndarray) -> bool:
        rel = relative_transform(torch.from_numpy(self.last_pose), torch.from_numpy(np.asarray(pose, np.float64)))
        _, R, t = sim3_decompose(rel)
        return float(t.norm()) > self.translation or float(so3_log(R).norm()) > self.rotation

    def state_dict(self) -> dict:
        return {"last_pose": self.last_pose, "frames_since": self.frames_since}

    def load_state_dict(self, d: dict) -> None:
        self.last_pose = None if d["last_pose"] is None else np.asarray(d["last_pose"], np.float64)
        self.frames_since = int(d["frames_since"])
