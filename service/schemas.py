"""Request and response bodies of the REST API (pydantic), shared with openapi.yaml."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

SessionStatus = Literal["created", "streaming", "finishing", "finished", "failed"]


class IntrinsicsIn(BaseModel):
    """Pinhole intrinsics of the streamed images, in pixels."""

    model_config = ConfigDict(extra="forbid")
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)

    @model_validator(mode="after")
    def _principal_point_inside(self) -> IntrinsicsIn:
        if not all(math.isfinite(v) for v in (self.fx, self.fy, self.cx, self.cy)):
            raise ValueError("intrinsics must be finite")
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise ValueError(f"principal point ({self.cx}, {self.cy}) lies outside the "
                             f"{self.width}x{self.height} image")
        return self


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    intrinsics: IntrinsicsIn | None = None
    preset: str | None = Field(default=None, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    name: str | None = Field(default=None, max_length=200)
    device_id: str | None = Field(default=None, max_length=200)
    metadata: dict[str, Any] = Field(default_factory=dict)


class Session(BaseModel):
    id: str
    name: str | None = None
    device_id: str | None = None
    status: SessionStatus
    created_at: str = Field(description="ISO 8601, UTC")
    updated_at: str = Field(description="ISO 8601, UTC")
    frames_received: int = Field(description="frames accepted into the session's queue")
    frames_processed: int = Field(description="frames the engine has tracked (each seq counted once)")
    frames_rejected: int = Field(0, description="accepted frames the worker refused (corrupt image, ...)")
    keyframes: int
    revision: int = Field(description="trajectory revision; grows when a loop closure rewrites past poses")
    worker: str | None = Field(None, description="id of the worker that owns (or last owned) the session")
    preset: str | None = None
    intrinsics: IntrinsicsIn | None = None
    metadata: dict[str, Any] = Field(default_factory=dict)
    error: str | None = Field(None, description="why the session failed")


class SessionList(BaseModel):
    sessions: list[Session]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last page")


class TrajectoryPose(BaseModel):
    seq: int
    timestamp: float
    pose: list[float] = Field(description="camera-to-world 4x4, 16 floats row-major")


class Trajectory(BaseModel):
    session_id: str
    revision: int
    which: Literal["all", "keyframes"]
    poses: list[TrajectoryPose]


class ErrorBody(BaseModel):
    detail: Any


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    status: Literal["ready", "not_ready"]
    redis: bool
    workers: int
