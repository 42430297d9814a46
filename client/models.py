"""What the SDK returns: sessions, saved maps, trajectories and live stream events, parsed from the server's JSON
(stream messages by `protocol.messages`: each event carries its typed message as `message`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.messages import (
    INPUT_EVENTS,
    MAP_EVENTS,
    TRACKING_EVENTS,
    LoopClosed,
    PoseMessage,
    ServerMessage,
    parse_server_message,
)


def pose_from_list(values: Any) -> np.ndarray:
    """A 4x4 float64 c2w matrix from the wire's 16 row-major floats (or a nested 4x4 list)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != 16:
        raise ValueError(f"a pose needs 16 values, got {arr.size}")
    return arr.reshape(4, 4)


def pose_to_list(pose: Any) -> list[float]:
    """The wire form of a 4x4 pose: 16 row-major floats. Rejects anything that is not 4x4 and finite."""
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape == (16,):
        arr = arr.reshape(4, 4)
    if arr.shape != (4, 4):
        raise ValueError(f"a pose must be a 4x4 matrix or 16 values, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("a pose must be finite")
    return [float(v) for v in arr.reshape(-1)]


@dataclass(frozen=True)
class Session:
    """A SLAM session as the gateway reports it. `raw` keeps every field the server sent."""

    id: str
    status: str
    name: str | None = None
    device_id: str | None = None
    created_at: Any = None
    updated_at: Any = None
    frames_received: int = 0
    frames_processed: int = 0
    frames_rejected: int = 0
    keyframes: int = 0
    revision: int = 0
    worker: str | None = None
    preset: str | None = None
    intrinsics: dict[str, Any] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    pose_mode: str | None = None
    estimated_intrinsics: dict[str, Any] | None = None  # the camera the engine uses: given, or estimated
    frames_skipped: int = 0  # skipped by the tracker under overload (newest first wins)
    skip_frames: bool = False  # whether the tracker may skip late frames (a live camera asks for it)
    tracking_state: str | None = None  # "tracking", "initializing", "lost" or "not_relocalized"
    mapping_lag_keyframes: int | None = None  # keyframes tracked but not yet mapped
    mapping_lag_s: float | None = None  # how long the oldest of them has waited
    tracking_side: int | None = None  # the tracking resolution's long side (None: the worker's default)
    frame_rate: float | None = None  # the camera's frame rate, as the client gave it
    settings: dict[str, Any] | None = None  # {preset, decided: auto|named, tracking_side, overrides, reasons}
    map_id: str | None = None  # the saved map the session runs in
    map_version: int | None = None  # that map's version (its latest when the session was created)
    map_mode: str | None = None  # "localize" or "extend"

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Session:
        if not isinstance(data, dict) or "id" not in data:
            raise ValueError(f"not a session object: {data!r}")
        return cls(
            id=str(data["id"]),
            status=str(data.get("status", "unknown")),
            name=data.get("name"),
            device_id=data.get("device_id"),
            created_at=data.get("created_at"),
            updated_at=data.get("updated_at"),
            frames_received=int(data.get("frames_received") or 0),
            frames_processed=int(data.get("frames_processed") or 0),
            frames_rejected=int(data.get("frames_rejected") or 0),
            keyframes=int(data.get("keyframes") or 0),
            revision=int(data.get("revision") or 0),
            worker=data.get("worker"),
            preset=data.get("preset"),
            intrinsics=data.get("intrinsics"),
            metadata=dict(data.get("metadata") or {}),
            error=data.get("error"),
            raw=dict(data),
            pose_mode=data.get("pose_mode"),
            estimated_intrinsics=data.get("estimated_intrinsics"),
            frames_skipped=int(data.get("frames_skipped") or 0),
            skip_frames=bool(data.get("skip_frames", False)),
            tracking_state=data.get("tracking_state"),
            mapping_lag_keyframes=data.get("mapping_lag_keyframes"),
            mapping_lag_s=data.get("mapping_lag_s"),
            tracking_side=data.get("tracking_side"),
            frame_rate=data.get("frame_rate"),
            settings=data.get("settings"),
            map_id=data.get("map_id"),
            map_version=data.get("map_version"),
            map_mode=data.get("map_mode"),
        )


@dataclass(frozen=True)
class SessionPage:
    """One page of the fleet listing; pass `next_cursor` back to get the next one (None: last page)."""

    sessions: list[Session]
    next_cursor: str | None


@dataclass(frozen=True)
class MapInfo:
    """A saved map as the gateway reports it: `meta` of its latest version (name, surfels, keyframes, bounds, scale,
    camera, mode, sessions, created_at); `versions` and `sessions` only from get_map / create_map / upload_map.
    `raw` keeps every field the server sent."""

    id: str
    name: str
    status: str
    latest_version: int
    size_bytes: int
    meta: dict[str, Any]
    created_at: str | None = None
    updated_at: str | None = None
    versions: list[dict[str, Any]] = field(default_factory=list)
    sessions: list[dict[str, Any]] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> MapInfo:
        if not isinstance(data, dict) or "id" not in data:
            raise ValueError(f"not a map object: {data!r}")
        return cls(id=str(data["id"]), name=str(data.get("name", "")), status=str(data.get("status", "unknown")),
                   latest_version=int(data.get("latest_version") or 0), size_bytes=int(data.get("size_bytes") or 0),
                   meta=dict(data.get("meta") or {}), created_at=data.get("created_at"),
                   updated_at=data.get("updated_at"), versions=list(data.get("versions") or []),
                   sessions=list(data.get("sessions") or []), raw=dict(data))


@dataclass(frozen=True)
class MapPage:
    """One page of the maps listing; pass `next_cursor` back to get the next one (None: last page)."""

    maps: list[MapInfo]
    next_cursor: str | None


@dataclass(frozen=True)
class TrajectoryPose:
    seq: int
    timestamp: float
    pose: np.ndarray  # 4x4 c2w similarity [sR|t]
    scale: float = 1.0  # s: pose[:3, :3] / scale is the rotation

    @property
    def position(self) -> np.ndarray:
        return self.pose[:3, 3]


@dataclass(frozen=True)
class Trajectory:
    """A session's estimated trajectory at one revision (the revision grows when a loop closure rewrites it)."""

    session_id: str
    revision: int
    which: str
    poses: list[TrajectoryPose]
    intrinsics: dict[str, Any] | None = None  # the camera of these poses: given, or estimated by the engine

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Trajectory:
        poses = [
            TrajectoryPose(seq=int(p.get("seq", i)), timestamp=float(p.get("timestamp", 0.0)),
                           pose=pose_from_list(p["pose"]), scale=float(p.get("scale", 1.0)))
            for i, p in enumerate(data.get("poses", []))
        ]
        return cls(session_id=str(data.get("session_id", "")), revision=int(data.get("revision") or 0),
                   which=str(data.get("which", "all")), poses=poses, intrinsics=data.get("intrinsics"))

    def __len__(self) -> int:
        return len(self.poses)

    def positions(self) -> np.ndarray:
        """Camera centres [N, 3]."""
        return np.array([p.position for p in self.poses]).reshape(-1, 3)


@dataclass(frozen=True)
class PoseEvent:
    """A live pose for a streamed frame (`message`: the server's message, typed)."""

    seq: int
    timestamp: float
    pose: np.ndarray  # 4x4 c2w similarity [sR|t]
    is_keyframe: bool
    revision: int
    scale: float = 1.0  # s: pose[:3, :3] / scale is the rotation
    message: PoseMessage | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class LoopClosedEvent:
    """The server closed a loop: trajectory revision `revision` rewrote past poses. `data`: the message as it came
    (fields this SDK does not know included); `message`: typed."""

    revision: int
    data: dict[str, Any] = field(default_factory=dict)
    message: LoopClosed | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class TrackingEvent:
    """The server's pose source changed state at frame `seq`: kind "tracking_lost" (poses hold the last good one
    until "relocalized"), "relocalized", "initializing" (RGB-only: waiting for parallax, `data["state"]`) or
    "initialized" (RGB-only: the first map; earlier frames' poses were re-estimated, see `data["revision"]`) or
    "new_map" (RGB-only: the old map was not found again, a new one begins at the last pose, `data["map"]`) or
    "maps_merged" (RGB-only: a map restarted after a loss was joined to the older one, scale included; the restarted
    map's poses moved, see `data["revision"]`) or "drift_corrected" (posed RGB, seeded: the pose graph was solved
    with the device's poses, moving past keyframes and the map toward them; RGB-D: with the newest keyframe's
    alignment to the keyframes near it, `source` covisibility; see `data["revision"]`) or
    "poses_refined" (at the end of a session: the final refinement moved the keyframes' cameras where the map's
    renders fit their photos, every frame following its keyframe; RGB-D frames tracked against a place come back to
    were put on its keyframe's final pose, `data["frames"]`; see `data["revision"]`) or "rotation_only"
    (RGB-only: a turn too fast for new points; poses follow the tracks' rotation, the position held or measured,
    `quality` at most 0.5). `data`: the message as it came; `message`: typed (`TRACKING_MESSAGES`), its fields
    documented in openapi.yaml."""

    kind: str
    seq: int
    data: dict[str, Any] = field(default_factory=dict)
    message: ServerMessage | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class InputEvent:
    """A notice about the session's input at frame `seq`; tracking goes on. Kind "pose_source_chosen" (posed RGB:
    the device poses judged over the first frames are kept as `prior` or only seed visual odometry, `seeded`; the
    judged frames were tracked again, see `data["revision"]` and `data["frames_replayed"]`), "device_pose_jump"
    (a device pose left out as a jump), "odometry_slip" (the odometry slipped where the device did not) or
    "depth_misregistered" (depth edges do not follow colour edges). `data`: the message as it came; `message`:
    typed (`INPUT_MESSAGES`)."""

    kind: str
    seq: int
    data: dict[str, Any] = field(default_factory=dict)
    message: ServerMessage | None = field(default=None, repr=False, compare=False)


# The server's messages each kind of SDK event stands for.
TRACKING_MESSAGES = TRACKING_EVENTS + MAP_EVENTS
INPUT_MESSAGES = INPUT_EVENTS
TRACKING_EVENT_TYPES = tuple(kind.TYPE for kind in TRACKING_MESSAGES)
INPUT_EVENT_TYPES = tuple(kind.TYPE for kind in INPUT_MESSAGES)
StreamEvent = PoseEvent | LoopClosedEvent | TrackingEvent | InputEvent


def event_from_message(message: dict[str, Any]) -> StreamEvent | None:
    """The SDK event for a server message of type "pose", "loop_closed", a tracking event or an input notice (None
    for others); ValueError when one of those lacks a field the protocol requires."""
    return stream_event(parse_server_message(message), message)


def stream_event(parsed: ServerMessage | None, message: dict[str, Any]) -> StreamEvent | None:
    """The SDK event for `parsed`, the typed form of the server message `message` (None: not an event)."""
    if isinstance(parsed, PoseMessage):
        return PoseEvent(seq=int(parsed.seq), timestamp=float(parsed.timestamp), pose=pose_from_list(parsed.pose),
                         is_keyframe=bool(parsed.is_keyframe), revision=int(parsed.revision),
                         scale=float(parsed.scale), message=parsed)
    if isinstance(parsed, LoopClosed):
        return LoopClosedEvent(revision=int(parsed.revision), data=dict(message), message=parsed)
    if isinstance(parsed, TRACKING_MESSAGES):
        return TrackingEvent(kind=parsed.TYPE, seq=int(parsed.seq), data=dict(message), message=parsed)
    if isinstance(parsed, INPUT_MESSAGES):
        return InputEvent(kind=parsed.TYPE, seq=int(parsed.seq), data=dict(message), message=parsed)
    return None


@dataclass
class StreamSummary:
    """What happened during one streaming run."""

    session_id: str
    frames_sent: int = 0
    frames_acked: int = 0
    poses: list[PoseEvent] = field(default_factory=list)
    loop_closures: list[LoopClosedEvent] = field(default_factory=list)
    tracking_events: list[TrackingEvent] = field(default_factory=list)
    input_events: list[InputEvent] = field(default_factory=list)
    backpressure_retries: int = 0
    frames_dropped: int = 0  # refused for backpressure after a later frame got in: re-sending would reorder
    errors: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)  # seqs the tracker skipped under overload (no pose for them)
    finished_frames: int | None = None
    elapsed_s: float = 0.0
    max_queue_depth: int = 0
    reconnects: int = 0  # connections re-opened after a break (the stream caught up each time)

    @property
    def fps(self) -> float:
        return self.frames_sent / self.elapsed_s if self.elapsed_s > 0 else 0.0
