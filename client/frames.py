"""The frames the SDK streams, without torch: any object with the `FrameLike` attributes will do
(`worker.data.frame.Frame` among them); `StreamFrame` is the SDK's own."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np


class Camera(Protocol):
    """Pinhole intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float


class FrameLike(Protocol):
    """What `encode_frame_message` reads from a frame."""

    timestamp: float
    image: np.ndarray
    intrinsics: Any
    depth: np.ndarray | None
    pose: np.ndarray | None


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (what a frame message's `intrinsics` carries)."""

    fx: float
    fy: float
    cx: float
    cy: float


@dataclass
class StreamFrame:
    """One frame to stream. image: uint8 RGB [H, W, 3]; depth: metric float [H, W] (0 = none); pose: camera-to-world
    4x4 from the device."""

    index: int
    timestamp: float
    image: np.ndarray
    intrinsics: Camera | None = None
    depth: np.ndarray | None = None
    pose: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[2] != 3 or self.image.dtype != np.uint8:
            raise ValueError(f"StreamFrame.image must be uint8 [H, W, 3], got {self.image.dtype} {self.image.shape}")
        if self.depth is not None and self.depth.shape != self.image.shape[:2]:
            raise ValueError(f"StreamFrame.depth must be {list(self.image.shape[:2])}, got {list(self.depth.shape)}")
        if self.pose is not None and np.asarray(self.pose).shape != (4, 4):
            raise ValueError("StreamFrame.pose must be a 4x4 matrix")


def is_frame(item: Any) -> bool:
    """Whether `item` has what a frame message needs (an RGB image and a timestamp)."""
    return isinstance(getattr(item, "image", None), np.ndarray) and hasattr(item, "timestamp")
