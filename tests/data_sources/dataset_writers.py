"""Tiny dataset folders in each supported layout, written with cv2 into tmp dirs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def write_image(path: Path, width: int = 32, height: int = 24, value: int = 0) -> np.ndarray:
    """A distinct RGB image (a gradient plus `value`), written as BGR; returns the RGB array."""
    path.parent.mkdir(parents=True, exist_ok=True)
    xs = np.linspace(0, 200, width, dtype=np.float32)
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[..., 0] = (xs[None, :] + value) % 256
    rgb[..., 1] = value % 256
    rgb[..., 2] = np.linspace(0, 100, height, dtype=np.float32)[:, None]
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return rgb


def write_depth(path: Path, metres: np.ndarray, scale: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.round(metres * scale).astype(np.uint16))


def translation_pose(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = [x, y, z]
    return pose
