"""Request and response bodies of the REST API (pydantic), shared with openapi.yaml."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    StrictBool,
    model_serializer,
    model_validator,
)

from protocol.keys import SessionStatus
from protocol.lens import RADTAN, distortion_problem
from protocol.limits import MAX_IMAGE_SIDE
from protocol.map_package import MapScale
from protocol.map_store import MapMode, MapStatus, SessionRole
from protocol.presets import PresetName
from service.presets import preset_field_description

PoseMode = Literal["prior", "fixed", "ignore", "seeded"]
POSE_MODE_DOC = ("what the engine does with the device poses frames carry (default: `seeded` when the frames carry "
                 "depth, else `prior` where the first frames show that the poses agree with the images and `seeded` "
                 "where they do not, said by a `pose_source_chosen` message): `prior` uses them as the odometry, "
                 "refined by loop closures, `fixed` keeps them exactly as sent (accurate ARKit/ARCore poses: no loop "
                 "correction), `ignore` tracks from the images (and depth) alone, `seeded` tracks from the images "
                 "(RGB-D or visual odometry) starting from the device's motion, with the device poses as priors in "
                 "the pose graph; a device pose that jumps (relocalisation) gets a `device_pose_jump` message and is "
                 "left out")
# A depth camera sits centimetres from the colour one: a longer translation is a unit mistake (Azure Kinect's
# calibration is in millimetres).
MAX_DEPTH_BASELINE_M = 1.0


# Request bodies take the JSON types their schema names, as JSON Schema reads them: pydantic's lax mode would also
# take "64" or true for an integer, 0 for a boolean, "1.5" for a number (schemathesis: schema-violating requests
# accepted). A number may be an integer; an integer may be written 64.0 (JSON Schema's integer is a value).
def _integral(value: Any) -> Any:
    return int(value) if isinstance(value, float) and value.is_integer() else value


def json_int(**constraints: Any) -> Any:
    """An integer field's type; `constraints` (ge, le, ...) stand before the validator, where pydantic's schema
    keeps them as JSON Schema keywords."""
    return Annotated[int, Strict(), Field(**constraints), BeforeValidator(_integral)]


JsonFloat = Annotated[float, Strict()]


class DistortionIn(BaseModel):
    """The lens distortion of the streamed images, in OpenCV's models with each coefficient named: `radtan`
    (radial-tangential: k1 k2 p1 p2 k3; phones, webcams, COLMAP's OPENCV camera) or `fisheye` (equidistant: k1-k4;
    COLMAP's OPENCV_FISHEYE). Coefficients not given are 0. The worker undistorts each frame once, before tracking,
    to a pinhole camera of the same size (the session's `estimated_intrinsics`: render with these)."""

    model_config = ConfigDict(extra="forbid")
    model: Literal["radtan", "fisheye"] = Field(RADTAN, description="radtan (the default) or fisheye")
    k1: JsonFloat | None = None
    k2: JsonFloat | None = None
    k3: JsonFloat | None = None
    k4: JsonFloat | None = Field(None, description="fisheye only")
    p1: JsonFloat | None = Field(None, description="radtan only (tangential)")
    p2: JsonFloat | None = Field(None, description="radtan only (tangential)")

    def wire(self) -> dict[str, Any]:
        """The coefficients given, with the model: the dict `protocol.lens` reads."""
        return {key: value for key, value in self.model_dump().items() if value is not None}

    @model_serializer(mode="wrap")
    def _coefficients_given(self, handler):  # no return annotation: the schema stays the model's
        return {key: value for key, value in handler(self).items() if value is not None}


class IntrinsicsIn(BaseModel):
    """Intrinsics of the streamed images, in pixels: the pinhole camera, and its lens distortion if any."""

    model_config = ConfigDict(extra="forbid")
    fx: JsonFloat = Field(gt=0)
    fy: JsonFloat = Field(gt=0)
    cx: JsonFloat
    cy: JsonFloat
    width: json_int(gt=0, le=MAX_IMAGE_SIDE)
    height: json_int(gt=0, le=MAX_IMAGE_SIDE)
    distortion: DistortionIn | None = Field(
        None, description="the lens distortion of the images as sent (null: none, or images already undistorted)")

    @model_serializer(mode="wrap")
    def _pinhole_without_null_lens(self, handler):  # no return annotation: the schema stays the model's
        out = handler(self)
        if out.get("distortion") is None:
            out.pop("distortion", None)
        return out

    @model_validator(mode="after")
    def _principal_point_inside(self) -> IntrinsicsIn:
        if not all(math.isfinite(v) for v in (self.fx, self.fy, self.cx, self.cy)):
            raise ValueError("intrinsics must be finite")
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise ValueError(f"principal point ({self.cx}, {self.cy}) lies outside the "
                             f"{self.width}x{self.height} image")
        if self.distortion is not None:
            problem = distortion_problem(self.distortion.wire(), self.fx, self.fy, self.cx, self.cy, self.width,
                                         self.height)
            if problem:
                raise ValueError(problem)
        return self


def _rigid_problem(T: list[list[float]]) -> str | None:
    """Why T (4x4, rows) is not a rigid transform with its translation in metres; None when it is one."""
    if len(T) != 4 or any(len(row) != 4 for row in T):
        return "must be a 4x4 matrix (rows)"
    if not all(math.isfinite(v) for row in T for v in row):
        return "must be finite"
    if any(abs(a - b) > 1e-6 for a, b in zip(T[3], (0.0, 0.0, 0.0, 1.0))):
        return "its last row must be [0, 0, 0, 1]"
    R = [row[:3] for row in T[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(R[k][i] * R[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                return "its rotation part is not a rotation (orthonormal)"
    det = (R[0][0] * (R[1][1] * R[2][2] - R[1][2] * R[2][1]) - R[0][1] * (R[1][0] * R[2][2] - R[1][2] * R[2][0])
           + R[0][2] * (R[1][0] * R[2][1] - R[1][1] * R[2][0]))
    if det < 0.99:
        return "its rotation part is a reflection (determinant -1)"
    baseline = math.sqrt(sum(T[i][3] ** 2 for i in range(3)))
    if baseline > MAX_DEPTH_BASELINE_M:
        return (f"its translation is {baseline:g} long: give it in metres (a depth camera sits centimetres from the "
                "colour one; Azure Kinect reports millimetres: divide by 1000)")
    return None


class DepthCameraIn(BaseModel):
    """The depth camera of an RGB-D sensor whose depth is not registered to the colour image (Kinect v1, RealSense
    without alignment, Azure Kinect): its pinhole intrinsics and the depth-to-colour extrinsic as the SDK reports
    it, either `depth_to_color` (4x4, rows) or `rotation` (3x3, rows) + `translation` (3), in metres. The worker then
    moves every depth pixel into the colour image before use."""

    model_config = ConfigDict(extra="forbid")
    intrinsics: IntrinsicsIn = Field(description="of the depth image (scaled to the depth PNGs' size when it differs)")
    depth_to_color: list[list[JsonFloat]] | None = Field(
        None, description="4x4 rigid transform taking depth-camera points to colour-camera points, rows, metres")
    rotation: list[list[JsonFloat]] | None = Field(None, description="3x3, rows (with `translation`)")
    translation: list[JsonFloat] | None = Field(None, description="3, metres (with `rotation`)")

    @model_validator(mode="after")
    def _one_rigid_extrinsic(self) -> DepthCameraIn:
        if self.depth_to_color is not None and (self.rotation is not None or self.translation is not None):
            raise ValueError("give depth_to_color or rotation + translation, not both")
        if self.depth_to_color is None:
            if self.rotation is None or self.translation is None:
                raise ValueError("give the depth-to-colour extrinsic: depth_to_color (4x4), or rotation (3x3) and "
                                 "translation (3)")
            if len(self.rotation) != 3 or any(len(row) != 3 for row in self.rotation) or len(self.translation) != 3:
                raise ValueError("rotation must be 3x3 and translation 3 long")
            self.depth_to_color = [[*self.rotation[i], self.translation[i]] for i in range(3)] + [[0.0, 0.0, 0.0,
                                                                                                   1.0]]
            self.rotation = self.translation = None
        problem = _rigid_problem(self.depth_to_color)
        if problem:
            raise ValueError(f"depth-to-colour extrinsic {problem}")
        return self


DEPTH_CAMERA_DOC = ("RGB-D sensors whose depth is not registered to the colour image: the depth camera's intrinsics "
                    "and depth-to-colour extrinsic; depth is registered to the colour camera before use. Without it, "
                    "the worker compares depth and colour edges over the first frames and reports a misregistration "
                    "(a `depth_misregistered` message and the session's `warnings`)")

TRACKING_SIDE_DOC = (
    "the tracking resolution: frames whose long side is larger are tracked at this long side (the pose is the same "
    "at any size; the map keeps the frames' working resolution), e.g. 320 to track a 640x480 camera at 30 frames/s "
    "on a CPU; null: the worker's default (FLASHMONO_TRACKING_SIDE, else the frames as they come)")

SKIP_FRAMES_DOC = (
    "true for a live camera: when tracking falls behind, a frame that waited longer than the worker's limit (100 ms) "
    "while a newer one is waiting gets a `skipped` message instead of a pose (newest first wins, a few in a row at "
    "most), so poses keep up with the camera; false (the default): every frame is tracked however late (recorded "
    "data, and clients that need every pose)")


FRAME_RATE_DOC = (
    "the camera's frame rate in frames/s, where the client knows it (a phone's camera: 30); the worker's choice of "
    "settings takes it into account and the session's `settings` names it")


MAP_ID_DOC = ("start the session in this saved map (GET /v1/maps): its version at creation (`map_version`); 422 for an "
              "unknown map, 403 for one this key may not read (`extend`: may not change)")
MAP_MODE_DOC = ("with `map_id`: `localize` (the default) tracks in the map and leaves it as it is; `extend` also maps "
                "what is new and adds a version to the map when the session finishes")


class SessionSettings(BaseModel):
    """The engine settings the session runs with: named by the client, or chosen by the worker."""

    preset: str = Field(description="the preset the engine runs")
    decided: Literal["auto", "named"] = Field(
        description="auto: chosen by the worker at the session's first frame from its input and machine; named: the "
        "client's preset")
    tracking_side: int | None = Field(None, description="the long side frames are tracked at (null: as they come, "
                                                        "or the session's own `tracking_side`)")
    working_side: int | None = Field(None, description="the long side frames are tracked and mapped at (a live "
                                                       "stream mapped on a CPU: 320; null: as they come); the "
                                                       "session's `estimated_intrinsics` are at this size")
    overrides: dict[str, Any] = Field(default_factory=dict, description="settings changed from the preset's")
    reasons: list[str] = Field(default_factory=list, description="why, one line each")


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    intrinsics: IntrinsicsIn | None = None
    preset: PresetName | None = Field(default=None, description=preset_field_description())
    pose_mode: PoseMode | None = Field(default=None, description=POSE_MODE_DOC)
    depth_camera: DepthCameraIn | None = Field(default=None, description=DEPTH_CAMERA_DOC)
    skip_frames: StrictBool = Field(default=False, description=SKIP_FRAMES_DOC)
    tracking_side: json_int(ge=64, le=4096) | None = Field(default=None, description=TRACKING_SIDE_DOC)
    frame_rate: JsonFloat | None = Field(default=None, gt=0, le=1000, description=FRAME_RATE_DOC)
    name: str | None = Field(default=None, max_length=200)
    device_id: str | None = Field(default=None, max_length=200)
    metadata: dict[str, Any] = Field(default_factory=dict)
    map_id: str | None = Field(default=None, max_length=64, description=MAP_ID_DOC)
    map_mode: MapMode | None = Field(default=None, description=MAP_MODE_DOC)

    @model_validator(mode="after")
    def _map_mode_needs_a_map(self) -> SessionCreate:
        if self.map_mode is not None and self.map_id is None:
            raise ValueError("map_mode needs map_id: the map to localize in or extend")
        return self


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
    frames_skipped: int = Field(
        0, description="frames the tracker skipped under overload (a newer frame was waiting: newest first wins); "
        "each got a `skipped` message instead of a pose")
    tracking_state: Literal["tracking", "initializing", "lost", "not_relocalized"] | None = Field(
        None, description="whether the newest processed frame was tracked (initializing: RGB only, waiting for "
        "parallax to make the first map; not_relocalized: a session in a map (`map_id`), tracked but not yet found "
        "in the map: its poses are in its own world until a `relocalized` message with the map's id, which "
        "revises them into the map's); null before the first frame")
    mapping_lag_keyframes: int | None = Field(
        None, description="keyframes tracked but not yet in the map (the mapping stage runs behind tracking)")
    mapping_lag_s: float | None = Field(None, description="seconds the oldest of those keyframes has waited")
    last_seq: int = Field(-1, description="the highest frame seq accepted so far (-1: none); a stream opened again "
                                          "(after a lost connection) continues after it")
    keyframes: int
    revision: int = Field(description="trajectory revision; grows when a loop closure rewrites past poses")
    worker: str | None = Field(None, description="id of the worker that owns (or last owned) the session")
    preset: str | None = Field(None, description="the preset the engine runs: as named, else as the worker chose it "
                                                "(null until the first frame)")
    settings: SessionSettings | None = Field(
        None, description="the settings the engine runs with and why (null until the worker has them: at the first "
        "frame when no preset was named)")
    frame_rate: float | None = Field(None, description=FRAME_RATE_DOC)
    pose_mode: PoseMode | None = Field(None, description="as created (null: the engine's default: seeded with depth, "
                                                         "else prior)")
    skip_frames: bool = Field(False, description=SKIP_FRAMES_DOC)
    tracking_side: int | None = Field(None, description=TRACKING_SIDE_DOC)
    intrinsics: IntrinsicsIn | None = None
    estimated_intrinsics: IntrinsicsIn | None = Field(
        None, description="the camera the engine uses at the frames' resolution: the given intrinsics, or the ones it "
        "estimated (monocular input without intrinsics); null until it knows them. Render with these to match the "
        "user's camera")
    metadata: dict[str, Any] = Field(default_factory=dict)
    error: str | None = Field(None, description="why the session failed")
    depth_camera: DepthCameraIn | None = Field(None, description="as created (the extrinsic as a 4x4 depth_to_color)")
    warnings: list[str] = Field(
        default_factory=list, description="what the worker noticed about the input, e.g. depth not registered to "
        "the colour image")
    map_id: str | None = Field(None, description="the saved map the session runs in (null: none)")
    map_version: int | None = Field(None, description="the map's version the session runs in: its latest when the "
                                                      "session was created")
    map_mode: MapMode | None = Field(None, description=MAP_MODE_DOC)


class SessionList(BaseModel):
    sessions: list[Session]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last page")


class TrajectoryPose(BaseModel):
    seq: int
    timestamp: float
    pose: list[float] = Field(description="camera-to-world similarity [sR|t; 0 0 0 1], 16 floats row-major: divide "
                              "the 3x3 block by `scale` for the rotation (before converting it to a quaternion)")
    scale: float = Field(1.0, description="s of the similarity: cbrt(|det(3x3 block)|); 1 with metric input")


class Trajectory(BaseModel):
    session_id: str
    revision: int
    which: Literal["all", "keyframes"]
    poses: list[TrajectoryPose]
    intrinsics: IntrinsicsIn | None = Field(
        None, description="the camera of these poses at the frames' resolution: given, or estimated by the engine "
        "(the session's estimated_intrinsics); null while unknown")


class ErrorBody(BaseModel):
    detail: Any


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    status: Literal["ready", "not_ready"]
    redis: bool
    workers: int


class PresetInfo(BaseModel):
    name: PresetName
    purpose: str
    input: str = Field(description="the input it suits")


class MachineChoices(BaseModel):
    machine: dict[str, Any] = Field(description="a worker's machine: cpu_cores, cuda, trained_weights")
    workers: int = Field(description="live workers on such a machine")
    live: dict[str, SessionSettings] = Field(
        description="per input mode (rgbd, posed-rgbd, posed-rgb, rgb): the settings `auto` chooses for a live "
        "640x480 stream (skip_frames true)")
    recorded: dict[str, SessionSettings] = Field(
        description="the same for recorded 640x480 frames (skip_frames false)")


class PresetList(BaseModel):
    presets: list[PresetInfo]
    auto_choices: list[MachineChoices] = Field(
        default_factory=list, description="what `auto` (no preset named) chooses on each kind of machine among the "
        "live workers")
    input_modes: str = Field(description="how the input mode follows from the fields a frame carries")


class MapCreate(BaseModel):
    """Save a finished session's map."""

    model_config = ConfigDict(extra="forbid")
    session_id: str = Field(max_length=64, description="a finished session this key created")
    name: str = Field(max_length=200)


class MapCamera(BaseModel):
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


class MapBounds(BaseModel):
    min: list[float] = Field(description="x, y, z")
    max: list[float] = Field(description="x, y, z")


class MapMeta(BaseModel):
    """What a map package holds (protocol.map_package)."""

    name: str = Field(description="as the package names it")
    surfels: int
    keyframes: int
    bounds: MapBounds | None = Field(description="the 1st-99th percentile box of the surfel centres, in map units "
                                                 "(null without surfels)")
    scale: MapScale = Field(description="metric (sensor depth or device poses: metres) or up_to_scale")
    camera: MapCamera = Field(description="the first keyframe's")
    mode: str = Field(description="the input mode of the session that built it: rgbd, posed-rgbd, posed-rgb, rgb")
    sessions: list[str] = Field(description="the sessions that built it (where it was built)")
    created_at: str = Field(description="ISO 8601, when the package was made")


class MapVersion(BaseModel):
    version: int
    created_at: str = Field(description="ISO 8601, UTC: when it was stored")
    size_bytes: int = Field(description="of the package")
    session_id: str | None = Field(description="the session that made it (null: uploaded)")
    meta: MapMeta


class MapSession(BaseModel):
    id: str
    role: SessionRole = Field(description="built: its map was saved as this map; used: created in the map")
    map_mode: MapMode | None = Field(description="used: how the session runs in the map")
    status: SessionStatus | None = Field(description="the session's status now (null: deleted)")


class MapSummary(BaseModel):
    id: str
    name: str
    status: MapStatus
    created_at: str = Field(description="ISO 8601, UTC")
    updated_at: str = Field(description="ISO 8601, UTC: the latest version's")
    latest_version: int
    size_bytes: int = Field(description="of the latest version's package")
    meta: MapMeta = Field(description="of the latest version")


class Map(MapSummary):
    versions: list[MapVersion] = Field(description="every version kept, oldest first")
    sessions: list[MapSession]


class MapList(BaseModel):
    maps: list[MapSummary]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last page")


class MapSessionList(BaseModel):
    map_id: str
    sessions: list[MapSession]
