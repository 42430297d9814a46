"""Keyframe selection from poses: the first frame, then every N frames or when the camera moved or turned enough
since the last keyframe (used where the pose source leaves the choice to the engine: given poses, RGB-D odometry).

A blurred frame makes a poor keyframe (its colours smear into the map and its depth is worse): when a keyframe is
due and the frame is markedly blurrier than the recent frames (sharpness below `blur_ratio` times their median),
the keyframe waits for the next frame, at most `blur_delay` frames. Sharpness is the variance of the Laplacian of
the grey image at low resolution (`sharpness`, a fraction of a millisecond per 320x240 frame).
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np
import torch

from worker.geometry import relative_transform, sim3_decompose, so3_log

SHARPNESS_SIDE = 160  # the longer side (pixels) at which sharpness is measured
SHARPNESS_HISTORY = 8  # recent frames whose median sharpness a frame is compared with
MIN_HISTORY = 3  # frames needed before a frame can be judged blurred


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (RGB uint8 [H, W, 3] or grey [H, W]) reduced to about
    SHARPNESS_SIDE pixels on its longer side: higher is sharper."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    h, w = grey.shape
    factor = max(1, round(max(h, w) / SHARPNESS_SIDE))
    if factor > 1:
        grey = cv2.resize(grey, (max(1, w // factor), max(1, h // factor)), interpolation=cv2.INTER_AREA)
    _, std = cv2.meanStdDev(cv2.Laplacian(grey, cv2.CV_32F))
    return float(std[0, 0]) ** 2


class MotionKeyframeSelector:
    """Decides, frame by frame, whether a pose starts a new keyframe (see the module docstring)."""

    def __init__(self, every: int, translation: float, rotation_deg: float, blur_ratio: float = 0.0,
                 blur_delay: int = 2) -> None:
        """`blur_ratio` 0 never delays a keyframe for blur."""
        self.every = every
        self.translation = translation
        self.rotation = math.radians(rotation_deg)
        self.blur_ratio = blur_ratio
        self.blur_delay = blur_delay
        self.last_pose: np.ndarray | None = None
        self.frames_since = 0
        self.delayed = 0  # frames the due keyframe has waited for a sharper one
        self.recent_sharpness: deque[float] = deque(maxlen=SHARPNESS_HISTORY)
        self._sharpness: float | None = None  # the current frame's, from `observe`

    def observe(self, image: np.ndarray) -> None:
        """Score the current frame's sharpness (before `is_keyframe` for that frame); without it, blur is not
        judged."""
        if self.blur_ratio > 0:
            self._sharpness = sharpness(image)

    def is_keyframe(self, pose: np.ndarray, force: bool = False) -> bool:
        """Whether `pose` (c2w 4x4) is a keyframe (always when `force`); updates the selector's state."""
        self.frames_since += 1
        score, self._sharpness = self._sharpness, None
        blurred = self._blurred(score)
        if score is not None:
            self.recent_sharpness.append(score)
        due = force or self.last_pose is None or self.frames_since >= self.every or self._moved(pose)
        if not due:
            return False
        if blurred and not force and self.last_pose is not None and self.delayed < self.blur_delay:
            self.delayed += 1
            return False
        self.last_pose = np.asarray(pose, np.float64).copy()
        self.frames_since = 0
        self.delayed = 0
        return True

    def _blurred(self, score: float | None) -> bool:
        """Whether the frame is markedly blurrier than the median of the recent frames."""
        if score is None or len(self.recent_sharpness) < MIN_HISTORY:
            return False
        return score < self.blur_ratio * float(np.median(self.recent_sharpness))

    def _moved(self, pose: np.ndarray) -> bool:
        rel = relative_transform(torch.from_numpy(self.last_pose), torch.from_numpy(np.asarray(pose, np.float64)))
        _, R, t = sim3_decompose(rel)
        return float(t.norm()) > self.translation or float(so3_log(R).norm()) > self.rotation

    def state_dict(self) -> dict:
        return {"last_pose": self.last_pose, "frames_since": self.frames_since, "delayed": self.delayed,
                "recent_sharpness": list(self.recent_sharpness)}

    def load_state_dict(self, d: dict) -> None:
        self.last_pose = None if d["last_pose"] is None else np.asarray(d["last_pose"], np.float64)
        self.frames_since = int(d["frames_since"])
        self.delayed = int(d.get("delayed", 0))
        self.recent_sharpness = deque((float(v) for v in d.get("recent_sharpness", [])), maxlen=SHARPNESS_HISTORY)
