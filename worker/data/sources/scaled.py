"""A sequence in other length units: every position and depth multiplied by one factor (`open_source(path,
scale=s)`, `flashmono run --scale S`).

The images and the camera are unchanged, so a SLAM system whose lengths follow the scene maps the scaled sequence
as it maps the original (the same renders, trajectories that differ by the factor): ICL at 0.1 is a doll's house
at 10-50 cm, at 10 a hall at 10-50 m. Device poses, ground truth and sensor depth are all scaled.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from worker.data.frame import Frame

from .base import DatasetError, FrameSource


def scaled_pose(pose: np.ndarray | None, scale: float) -> np.ndarray | None:
    """A camera-to-world pose with its translation multiplied by `scale` (None stays None)."""
    if pose is None:
        return None
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, 3] *= scale
    return out


class ScaledSource(FrameSource):
    """`source` with every pose, ground-truth pose and depth multiplied by `scale` (see the module docstring)."""

    def __init__(self, source: FrameSource, scale: float) -> None:
        if not (math.isfinite(scale) and scale > 0):
            raise DatasetError(f"scale must be a finite number > 0, got {scale!r}")
        super().__init__(source.options)
        self.source, self.scale = source, float(scale)
        self.name = f"{source.name} x{self.scale:g}"
        self.intrinsics = source.intrinsics

    def __len__(self) -> int:
        return len(self.source)  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[Frame]:
        for frame in self.source:
            depth = None if frame.depth is None else (frame.depth * np.float32(self.scale)).astype(np.float32)
            yield replace(frame, depth=depth, pose=scaled_pose(frame.pose, self.scale),
                          gt_pose=scaled_pose(frame.gt_pose, self.scale))
