"""The depth camera of an RGB-D session (`input.depth_camera`): its intrinsics and the depth-to-colour extrinsic."""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

# A depth camera sits centimetres from the colour one: a translation longer than this is a unit mistake (Azure
# Kinect's calibration is in millimetres).
MAX_BASELINE_M = 1.0


def rigid_transform_problem(matrix: list[list[float]]) -> str | None:
    """Why `matrix` is not a 4x4 rigid transform with a translation in metres (None when it is one)."""
    T = np.asarray(matrix, dtype=np.float64)
    if T.shape != (4, 4):
        return f"must be a 4x4 matrix, got shape {list(T.shape)}"
    if not np.all(np.isfinite(T)):
        return "must be finite"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return "its last row must be [0, 0, 0, 1]"
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0.99:
        return "its rotation part is not a rotation (orthonormal, determinant +1)"
    baseline = float(np.linalg.norm(T[:3, 3]))
    if baseline > MAX_BASELINE_M:
        return (f"its translation is {baseline:g} long: it must be in metres (a depth camera sits centimetres from "
                "the colour one; Azure Kinect reports millimetres: divide by 1000)")
    return None


class DepthCameraConfig(BaseModel):
    """Pinhole intrinsics of the depth image (any size: scaled to the frames' depth) and `depth_to_color`, the 4x4
    rigid transform taking depth-camera points to colour-camera points, in metres."""

    model_config = ConfigDict(extra="forbid")

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)
    depth_to_color: list[list[float]] = Field(description="4x4, rows; translation in metres")

    @model_validator(mode="after")
    def _valid(self) -> DepthCameraConfig:
        if not all(math.isfinite(v) for v in (self.fx, self.fy, self.cx, self.cy)):
            raise ValueError("depth intrinsics must be finite")
        problem = rigid_transform_problem(self.depth_to_color)
        if problem:
            raise ValueError(f"depth_to_color {problem}")
        return self
