"""The WebSocket messages, typed: what a client sends (`ClientMessage`) and what the gateway and the workers send
back (`ServerMessage`: results, acks, errors and the engine's events), with the error and close codes.

openapi.yaml's `x-websocket` is generated from these classes (`protocol.schema`, `service.websocket_doc`): a field,
its type and its description are written once, here. `to_dict()`/`to_json()` give the wire form, `type` first
(the gateway recognises `{"type": "finished"` by its prefix). The engine's events are sent through their classes
here (the worker's own, `worker.events`, subclass them with what only the engine keeps): each class declares every
field the engine sends, scalars only; `OPEN`, a newer server may add more, which `from_dict` drops.
"""

from __future__ import annotations

import json
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, Literal, get_args

from protocol.codec import pack, unpack

ErrorCode = Literal[
    "backpressure",
    "unavailable",
    "bad_seq",
    "bad_size",
    "bad_message",
    "bad_image",
    "bad_depth",
    "bad_pose",
    "bad_intrinsics",
    "too_large",
    "bad_frame",
    "not_accepting",
    "too_many_streams",
    "not_found",
    "unauthorized",
    "forbidden",
    "forbidden_origin",
    "engine_failed",
    "abandoned",
]

ERROR_CODES: dict[str, str] = {
    "backpressure": (
        "the session's queue is full (or an earlier frame was refused for it): not queued; re-send from `resend_from`"
    ),
    "unavailable": (
        "the session store (Redis) is unreachable: not queued; re-send from `resend_from` (with a seq) "
        "or reconnect (without)"
    ),
    "bad_seq": (
        "seq not greater than the last accepted one (duplicate or out of order): not queued; the message "
        "names the last accepted seq"
    ),
    "bad_size": "the image's size differs from the session's first frame's: not queued (one size per session)",
    "bad_message": (
        "not a msgpack map with type frame, a text frame, a bad seq/timestamp, or an unknown control message"
    ),
    "bad_image": (
        "image missing, not JPEG/PNG, too large a side, or corrupt (the last found by the worker after the ack)"
    ),
    "bad_depth": "depth is not a 16-bit PNG of the image's size",
    "bad_pose": "pose is not 16 finite floats of a rigid or similarity transform",
    "bad_intrinsics": "intrinsics malformed, or the session's are for another aspect ratio",
    "too_large": "the message exceeds FLASHMONO_MAX_FRAME_BYTES",
    "bad_frame": "the worker could not use an acked frame (the engine refused it)",
    "not_accepting": "the session is finishing or finished: not queued",
    "too_many_streams": "this gateway holds FLASHMONO_MAX_STREAMS open streams: retry shortly (then close 1013)",
    "not_found": "the session was deleted (then close 4404)",
    "unauthorized": "missing or unknown API key (then close 4401)",
    "forbidden": "the key lacks the stream scope or did not create the session (then close 4403)",
    "forbidden_origin": "a browser Origin not in FLASHMONO_ALLOWED_ORIGINS (then close 4403)",
    "engine_failed": "the session failed in the worker (status failed)",
    "abandoned": (
        "no frame for FLASHMONO_IDLE_TIMEOUT_S (600 s): the session is abandoned and its worker slot "
        "freed; opening its stream again within FLASHMONO_ABANDONED_GRACE_S (3600 s) resumes it"
    ),
}
"""Every `code` an `error` message can carry, and what it means."""

CLOSE_CODES: dict[str, str] = {
    "1000": "after `finished`: every frame was processed",
    "1009": (
        "a message larger than the server's WebSocket limit (about 2 x FLASHMONO_MAX_FRAME_BYTES); no error "
        "frame (the WebSocket layer closes)"
    ),
    "1013": (
        "try again later: the session store (Redis) is unreachable at connect time, or the gateway holds its "
        "FLASHMONO_MAX_STREAMS open streams"
    ),
    "4401": "unauthorized: missing or unknown key (header, or ?api_key=)",
    "4403": "forbidden: the key lacks the stream scope, did not create the session, or the Origin is not allowed",
    "4404": "the session does not exist or was deleted",
    "4409": "the session takes no frames (finishing, finished or failed)",
}
"""Every WebSocket close code the stream uses, and when."""

assert tuple(ERROR_CODES) == get_args(ErrorCode)
ERROR_CODE_DOC = "; ".join(f"{code}: {meaning}" for code, meaning in ERROR_CODES.items())


def info(*, doc: str = "", schema: dict[str, Any] | None = None, default: Any = MISSING) -> Any:
    """A message field with its description and JSON-schema details beyond its type (`protocol.schema`)."""
    return field(default=default, metadata={"doc": doc, "schema": schema or {}})


def at_frame() -> Any:
    """The optional `frame` of an engine event: the frame it is about, which may precede the one carrying it."""
    return info(doc=("the frame the engine found it at (its seq); `seq` is the frame whose result carried it, later "
                     "when the event waited for a verdict or a keyframe"), default=None)


def solve_error(when: str) -> Any:
    """The optional pose-graph error of an event a pose-graph solve made, `when` ("before"/"after") the solve."""
    return info(doc=f"the pose graph's error {when} the solve", default=None)


@dataclass(frozen=True, kw_only=True)
class Message:
    """One WebSocket message; subclasses set `TYPE` and declare the fields after `type`."""

    TYPE: ClassVar[str]
    DOC: ClassVar[str] = ""
    ENCODING: ClassVar[str] = "text JSON"
    OPEN: ClassVar[bool] = False  # the sender may add fields beyond those declared
    NOTES: ClassVar[dict[str, str]] = {}  # further documentation entries beside the schema

    def to_dict(self) -> dict[str, Any]:
        """The wire form: `type` first, then every field that is set (None fields are left out)."""
        out: dict[str, Any] = {"type": self.TYPE}
        for item in fields(self):
            value = getattr(self, item.name)
            if value is not None:
                out[item.name] = value
        return out

    def to_json(self) -> str:
        """The text frame of a JSON-encoded message."""
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Message:
        """The message for a wire dict of this type (fields it does not declare are dropped); ValueError when a field
        it requires is missing."""
        names = {item.name for item in fields(cls)}
        missing = [item.name for item in fields(cls)
                   if item.default is MISSING and item.default_factory is MISSING and item.name not in data]
        if missing:
            raise ValueError(f"a {cls.TYPE} message without {', '.join(missing)}")
        return cls(**{k: v for k, v in data.items() if k in names})


@dataclass(frozen=True, kw_only=True)
class ClientMessage(Message):
    """A message from the client to the gateway."""


@dataclass(frozen=True, kw_only=True)
class ServerMessage(Message):
    """A message from the gateway (or a worker, through the session's outbox) to the client."""


@dataclass(frozen=True, kw_only=True)
class FrameMessage(ClientMessage):
    TYPE: ClassVar[str] = "frame"
    ENCODING: ClassVar[str] = (
        "binary WebSocket message holding a msgpack map (text JSON frames are refused with bad_message)"
    )
    NOTES: ClassVar[dict[str, str]] = {
        "input_mode": (
            "the fields of the first frame choose the input mode for the session "
            "(see the `preset` field of POST /v1/sessions and GET /v1/presets)"
        )
    }
    seq: int = info(doc="strictly increasing, gaps allowed; see sequence_numbers", schema={"minimum": 0})
    timestamp: float = info(doc="seconds")
    image: bytes = info(doc="JPEG or PNG (RGB) as raw bytes; every frame of a session the same size")
    intrinsics: dict[str, float] | list[float] | None = info(
        doc=("overrides the session's intrinsics for this frame: {fx, fy, cx, cy} in pixels of this image; the "
             "session's lens distortion still applies unless the object names its own `distortion` ({model: "
             "radtan|fisheye, k1, k2, ...} as the session's intrinsics take it; null: none)"),
        schema={
            "oneOf": [
                {"type": "object", "required": ["fx", "fy", "cx", "cy"],
                 "properties": {"distortion": {"type": "object", "description": "as the session's intrinsics'"}}},
                {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
            ]
        },
        default=None,
    )
    depth: bytes | None = info(
        doc=("16-bit single-channel PNG in millimetres, same size as the image (0 = no depth)"), default=None
    )
    pose: list[float] | None = info(
        doc=("device pose, camera-to-world 4x4 row-major (rigid, metres); the session's pose_mode says how it is used"),
        schema={"minItems": 16, "maxItems": 16},
        default=None,
    )

    def encode(self) -> bytes:
        """The binary WebSocket message: a msgpack map."""
        return pack(self.to_dict())

    @classmethod
    def decode(cls, data: bytes, max_bytes: int | None = None) -> dict[str, Any]:
        """The msgpack map of a binary message, unchecked (ValueError when it is no msgpack)."""
        return unpack(data, max_bytes=max_bytes)


@dataclass(frozen=True, kw_only=True)
class FinishMessage(ClientMessage):
    TYPE: ClassVar[str] = "finish"
    DOC: ClassVar[str] = (
        "no more frames: the worker processes what is queued, then finishes the map with "
        "the preset's final refinement, if it has one, and sends finished and closes (code "
        "1000); render requests are answered after it. `rgbd` refines 8 passes over every "
        "held keyframe (at most 66: the window and 64 archived), about 0.1 s per keyframe "
        "and pass at 320x240 on 2 CPU cores: 30 s for the 211-frame ICL sequence (36 "
        "keyframes), up to about a minute for long sessions (bench/RESULTS.md). Meanwhile "
        "`finishing` messages come every 2 s and the session's status stays `finishing`"
    )


@dataclass(frozen=True, kw_only=True)
class PingMessage(ClientMessage):
    TYPE: ClassVar[str] = "ping"
    DOC: ClassVar[str] = "answered by {type: pong}"


@dataclass(frozen=True, kw_only=True)
class AckMessage(ServerMessage):
    TYPE: ClassVar[str] = "ack"
    DOC: ClassVar[str] = "the frame is queued (durably, in Redis)"
    seq: int
    queue_depth: int = info(doc="frames queued for the worker, this one included")


@dataclass(frozen=True, kw_only=True)
class PoseMessage(ServerMessage):
    TYPE: ClassVar[str] = "pose"
    DOC: ClassVar[str] = "the tracked pose of a frame: its result, sent once per seq"
    seq: int
    timestamp: float
    pose: list[float] = info(
        doc=(
            "camera-to-world similarity [sR | t; 0 0 0 1], 16 floats row-major (OpenCV "
            "camera: x right, y down, z forward). The 3x3 block is s times a rotation: "
            "divide it by `scale` before converting it to a quaternion. s = 1 with metric "
            "input (depth or device poses)"
        ),
        schema={"minItems": 16, "maxItems": 16},
    )
    scale: float = info(doc="s of the similarity: cbrt(|det(3x3 block)|)")
    is_keyframe: bool
    revision: int


@dataclass(frozen=True, kw_only=True)
class SkippedMessage(ServerMessage):
    TYPE: ClassVar[str] = "skipped"
    DOC: ClassVar[str] = (
        "the result of a frame the tracker skipped: it waited longer than the worker's skip "
        "limit (FLASHMONO_SKIP_AFTER_MS, 100 ms) while a newer frame was waiting, so the "
        "newer one was tracked instead (newest first wins, a few in a row at most); no pose "
        "comes for this seq"
    )
    seq: int
    reason: Literal["overload"]


@dataclass(frozen=True, kw_only=True)
class LoopClosed(ServerMessage):
    TYPE: ClassVar[str] = "loop_closed"
    DOC: ClassVar[str] = "a loop closure rewrote past poses: GET the trajectory for revision `revision`"
    OPEN: ClassVar[bool] = True
    revision: int
    from_keyframe: int | None = info(doc="the newest keyframe of the loop (the one that recognised the place)",
                                     default=None)
    to_keyframe: int | None = info(doc="the older keyframe it recognised", default=None)
    source: str | None = info(doc="how the loop was verified (pnp, pnp_xfeat, hidden_state)", default=None)
    scale: float | None = info(doc="the loop edge's scale change (1 with metric input)", default=None)
    pgo_error_before: float | None = solve_error("before")
    pgo_error_after: float | None = solve_error("after")


@dataclass(frozen=True, kw_only=True)
class TrackingLost(ServerMessage):
    TYPE: ClassVar[str] = "tracking_lost"
    DOC: ClassVar[str] = (
        "the pose source lost the camera (a black, textureless or blurred view, no depth, a "
        "sudden jump): until `relocalized`, poses hold the last good one and no keyframes "
        "are made; never a silent jump (seeded sessions with depth: poses follow the "
        "device's motion and, once lost for `device_poses.resume_after_s`, the odometry "
        "restarts at the device's pose: `relocalized` with method device_pose)"
    )
    OPEN: ClassVar[bool] = True
    seq: int = info(doc="the frame it is at")
    reason: str | None = None
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class Relocalized(ServerMessage):
    TYPE: ClassVar[str] = "relocalized"
    DOC: ClassVar[str] = (
        "tracking is back at frame `seq`, placed against an earlier keyframe (`method`: "
        "how; device_pose: a seeded session's odometry restarted where the device's pose "
        "says the camera is); or, a session created in a saved map, found in that map "
        "(`map_id`, its `keyframe`): the session's world moved into the map's, its earlier "
        "poses too (`revision`)"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    frame: int | None = at_frame()
    method: str | None = info(
        default=None,
        doc="how tracking came back: absent for a short loss (the last tracked frame's points found again); place "
        "recognition, learned, learned keyframe, learned glue (visual odometry against a remembered keyframe), "
        "reinitialized (a new map from two views scaled to the old), device (device poses again), device_pose (a "
        "seeded session's odometry restarted at the device's pose), photo registration (a photo session registers "
        "photos again), registered later (a photo session placed photos it had reported lost: `lost_frames` of "
        "them, the trajectory revised at `revision`)",
    )
    reason: str | None = info(doc="device_pose: why the odometry was restarted", default=None)
    place: int | None = info(doc="visual odometry: the earlier frame it was placed against", default=None)
    keyframe: int | None = info(
        doc="the keyframe it was placed against (RGB-D odometry; a saved map: the map's keyframe)", default=None
    )
    map_id: str | None = info(
        doc="the saved map the session was relocalized in (a session started in a saved map); absent: its own map",
        default=None,
    )
    inliers: int | None = info(
        doc="correspondences that placed the camera (PnP inliers; reinitialized: the two-view points)", default=None
    )
    reprojection_px: float | None = info(doc="the inliers' reprojection error (RMS), pixels", default=None)
    matches: int | None = info(doc="a saved map: the matches the inliers were found among", default=None)
    depth_agreement: float | None = info(
        doc="a saved map, frames with depth: the share of the inliers whose depth agrees with the map's",
        default=None,
    )
    revision: int | None = info(
        doc="a saved map: the session moved into the map's world, its earlier poses too: GET the trajectory for "
        "revision `revision`",
        default=None,
    )
    lost_frames: int | None = info(doc="frames tracking was lost for", default=None)
    model: str | None = info(doc="reinitialized: the two-view model (homography or essential)", default=None)
    scale_from: str | None = info(
        doc="reinitialized: what scaled the new map to the old (shared points or scene depth)", default=None
    )
    shared_points: int | None = info(doc="reinitialized: old map points the two views share", default=None)


@dataclass(frozen=True, kw_only=True)
class Initializing(ServerMessage):
    TYPE: ClassVar[str] = "initializing"
    DOC: ClassVar[str] = (
        "RGB-only sessions: visual odometry is waiting to make its first map (`state` "
        "waiting_for_parallax or rotation_only: the camera only turned, so poses carry its "
        "orientation and hold the position; `model` homography or essential); sent when the "
        "state changes, `initialized` follows"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    state: str | None = None
    reason: str | None = None
    model: str | None = None
    score_ratio: float | None = info(doc="how much better the homography fits than the essential matrix",
                                     default=None)
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class Initialized(ServerMessage):
    TYPE: ClassVar[str] = "initialized"
    DOC: ClassVar[str] = (
        "RGB-only sessions: visual odometry made its first map at frame `seq`; the frames "
        "before it, sent at the first frame's pose, were re-estimated: GET the trajectory "
        "for revision `revision`. After a `new_map` (`map` > 1), `registered_frames` are "
        "the frames reported lost while it waited, now posed in the new map (they move with "
        "it when a loop joins the maps)"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    revision: int | None = None
    frames_revised: int | None = None
    frame: int | None = at_frame()
    map: int | None = info(doc="the map's number (1: the session's first)", default=None)
    points: int | None = info(doc="map points the two views triangulated", default=None)
    parallax_deg: float | None = info(doc="the two views' median parallax", default=None)
    model: str | None = info(doc="the two-view model (homography or essential)", default=None)
    score_ratio: float | None = info(doc="how much better the homography fits than the essential matrix",
                                     default=None)
    focal_trusted: bool | None = info(
        doc="RGB-D sessions without intrinsics: whether the focal length estimated from the first frames is trusted",
        default=None,
    )


@dataclass(frozen=True, kw_only=True)
class NewMap(ServerMessage):
    TYPE: ClassVar[str] = "new_map"
    DOC: ClassVar[str] = (
        "RGB-only sessions: after a loss nothing could bridge (a jump to an unseen view), "
        "visual odometry begins map number `map` at the last pose, with the old map's scene "
        "depth; `initializing` and `initialized` follow, and a `loop_closed` joining the "
        "two maps moves it into place (a new trajectory revision)"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    map: int | None = None
    lost_frames: int | None = None
    scene_depth: float | None = info(doc="the old map's median scene depth the new one starts with", default=None)
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class RotationOnly(ServerMessage):
    TYPE: ClassVar[str] = "rotation_only"
    DOC: ClassVar[str] = (
        "RGB-only sessions: a turn too fast for new points to be triangulated; from frame "
        "`seq` the poses follow the rotation every track agrees on, the position from the "
        "map points still seen (or held), with `quality` at most 0.5, until the tracks "
        "measure map points again (no event: `quality` rises) or tracking is lost"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    tracks: int | None = info(doc="tracks that agree on the rotation", default=None)
    map_points: int | None = info(doc="map points that measured the position (0: held)", default=None)
    method: Literal["photometric"] | None = info(
        doc=(
            "present when no track survived (a fast turn over weak or striped texture): the "
            "turn comes from aligning the whole image, `quality` at most 0.4"
        ),
        default=None,
    )
    correlation: float | None = None
    measured_axes: int | None = info(
        doc=("photometric: rotation axes the image measured (the others follow the predicted turn)"), default=None
    )
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class MapsMerged(ServerMessage):
    TYPE: ClassVar[str] = "maps_merged"
    DOC: ClassVar[str] = (
        "RGB-only sessions: a map visual odometry restarted after `tracking_lost` "
        "recognised a place of the older map; a Sim(3) edge joined the two in the pose "
        "graph and the restarted map's poses moved into the older map's frame, scale "
        "included: GET the trajectory for revision `revision`"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    revision: int | None = None
    place: int | None = info(doc="the older frame the restarted map recognised", default=None)
    since: int | None = info(doc="the first frame of the restarted map", default=None)
    scale: float | None = info(doc="how much the restarted map was scaled to fit", default=None)
    frame: int | None = at_frame()
    method: str | None = info(doc="how the place was recognised (orb or learned)", default=None)
    pairs: int | None = info(doc="point pairs that measured the join", default=None)
    spread: float | None = None
    from_keyframe: int | None = info(doc="the restarted map's keyframe that recognised the place", default=None)
    to_keyframe: int | None = info(doc="the older map's keyframe it was joined to", default=None)
    pgo_error_before: float | None = solve_error("before")
    pgo_error_after: float | None = solve_error("after")


@dataclass(frozen=True, kw_only=True)
class DriftCorrected(ServerMessage):
    TYPE: ClassVar[str] = "drift_corrected"
    DOC: ClassVar[str] = (
        "posed RGB sessions where the device poses seed visual odometry (pose_source "
        "seeded): the pose graph was solved with the device's keyframe poses as priors, "
        "correcting the odometry's drift (its scale above all) between loop closures; past "
        "keyframes and their part of the map moved: GET the trajectory for revision "
        "`revision`. Sessions in a saved map: the same with the keyframes' fixes in the map "
        "as priors (`source` map). RGB-D sessions: the newest keyframe was aligned to the older "
        "keyframes near it, image and depth, and the graph solved with those edges (`source` "
        "covisibility)"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    revision: int | None = None
    keyframe: int | None = info(doc="the newest keyframe whose device pose (or fix, or edges) was used", default=None)
    source: str | None = info(
        doc=("map: the priors are the keyframes' fixes in the saved map the session runs in; covisibility: the "
             "edges of an RGB-D keyframe to its neighbours (absent: device poses)"),
        default=None,
    )
    from_other_sessions: int | None = info(
        doc=("map: how many of these priors are fixes among the keyframes other sessions extending the map shared "
             "live (a loop between two devices; absent: none)"),
        default=None,
    )
    pgo_error_before: float | None = solve_error("before")
    pgo_error_after: float | None = solve_error("after")


@dataclass(frozen=True, kw_only=True)
class PosesRefined(ServerMessage):
    TYPE: ClassVar[str] = "poses_refined"
    DOC: ClassVar[str] = (
        "sent once while a session finishes, before `finished`, when its last step moved "
        "poses: with `mapping.final_refine_poses` on, the final refinement moved the keyframes' "
        "cameras where the map's renders fit their photos (photometric bundle adjustment; "
        "never with pose_mode fixed), every frame following its keyframe; and frames tracked "
        "against an earlier keyframe the camera came back to (RGB-D) were put on that "
        "keyframe's final pose: GET the trajectory for revision `revision`"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    revision: int | None = None
    keyframes: int | None = info(doc="how many keyframes' cameras moved", default=None)
    frames: int | None = info(doc="how many frames were put on the earlier keyframe they were tracked against",
                              default=None)


@dataclass(frozen=True, kw_only=True)
class DevicePoseJump(ServerMessage):
    TYPE: ClassVar[str] = "device_pose_jump"
    DOC: ClassVar[str] = (
        "pose_mode seeded: the device pose of frame `seq` jumped (ARKit/ARCore "
        "relocalising, a glitch); the session's poses do not follow the jump and the next "
        "keyframe gets no device prior"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    translation: float | None = info(
        doc=("how far the device's motion into this frame is from the tracked motion (pose units)"), default=None
    )
    rotation_deg: float | None = None
    action: str | None = info(doc="what the session did about it", default=None)
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class PoseSourceChosen(ServerMessage):
    TYPE: ClassVar[str] = "pose_source_chosen"
    DOC: ClassVar[str] = (
        "pose_mode auto, frames with poses and no depth: over the first frames (at most "
        "input.pose_choice.within_frames, 30) the device poses were judged against the "
        "images (meanwhile frames get the device's poses, provisionally, and no keyframe); "
        "`prior`: they are the odometry; `seeded`: visual odometry tracks from the device's "
        "motion, the device poses are pose-graph priors (also in the session's warnings); "
        "either way the judged frames go through the chosen source from the first"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    pose_source: Literal["prior", "seeded"] | None = None
    reason: str | None = None
    reprojection_px: float | None = info(
        doc=("median three-view reprojection error of tracked corners with the device's poses"), default=None
    )
    fitted_px: float | None = info(doc="... with poses fitted to the same tracks", default=None)
    ratio: float | None = None
    max_ratio: float | None = None
    triples: int | None = info(doc="frame triples measured", default=None)
    agree: bool | None = info(
        doc="null: too few triples to judge by", schema={"type": ["boolean", "null"]}, default=None
    )
    frames_replayed: int | None = info(
        doc="the judged frames, tracked again by the chosen source from the first", default=None
    )
    revision: int | None = info(doc="the trajectory revision with their new poses", default=None)
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class OdometrySlip(ServerMessage):
    TYPE: ClassVar[str] = "odometry_slip"
    DOC: ClassVar[str] = (
        "pose_mode seeded with depth: the device and the RGB-D odometry disagreed on frame "
        "`seq` and the images sided with the device (the odometry had settled in a wrong "
        "place): the frame was tracked again from the device's motion; no device jump"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    photometric_rms: list[float] | None = info(
        doc=(
            "robust intensity residual of the odometry's pose, then of the pose tracked again from the device's motion"
        ),
        default=None,
    )
    geometric_rms: list[float] | None = None
    action: str | None = info(doc="what the session did about it", default=None)
    frame: int | None = at_frame()


@dataclass(frozen=True, kw_only=True)
class DepthMisregistered(ServerMessage):
    TYPE: ClassVar[str] = "depth_misregistered"
    DOC: ClassVar[str] = (
        "sessions without depth_camera: over the first frames, depth edges fit colour edges "
        "best shifted by (shift_dx, shift_dy) pixels: colour and depth are not registered "
        "(also in the session's warnings); create the session with depth_camera"
    )
    OPEN: ClassVar[bool] = True
    seq: int
    shift_dx: int | None = None
    shift_dy: int | None = None
    message: str | None = None
    agreement: float | None = info(
        doc="mean normalised colour gradient on depth edges at the best shift", default=None
    )
    agreement_unshifted: float | None = info(doc="... at no shift", default=None)


@dataclass(frozen=True, kw_only=True)
class ExtendOutcome(ServerMessage):
    """What came of a session created in a saved map with map_mode extend, told at its finish."""

    OPEN: ClassVar[bool] = True
    seq: int = info(doc="the last frame")
    map_id: str


@dataclass(frozen=True, kw_only=True)
class MapExtended(ExtendOutcome):
    TYPE: ClassVar[str] = "map_extended"
    DOC: ClassVar[str] = "extend sessions: the session's map was joined to the saved map's newest version as `version`"
    version: int
    keyframes: int | None = info(doc="keyframes of the new version", default=None)


@dataclass(frozen=True, kw_only=True)
class MapNotExtended(ExtendOutcome):
    TYPE: ClassVar[str] = "map_not_extended"
    DOC: ClassVar[str] = "extend sessions: the session's map was not added to the saved map, which stays as it was"
    reason: str = info(doc="why: never relocalized in the map, the map deleted, ...")


@dataclass(frozen=True, kw_only=True)
class ErrorMessage(ServerMessage):
    TYPE: ClassVar[str] = "error"
    DOC: ClassVar[str] = (
        "a refused or unusable frame (never silently dropped) or a session-level problem; "
        "the stream stays open except where close_codes says otherwise"
    )
    code: ErrorCode = info(doc=ERROR_CODE_DOC)
    message: str
    seq: int | None = info(doc="the frame it is about", default=None)
    queue_depth: int | None = info(doc="with backpressure", default=None)
    resend_from: int | None = info(doc="with backpressure/unavailable: the seq to re-send next", default=None)


@dataclass(frozen=True, kw_only=True)
class FinishingMessage(ServerMessage):
    TYPE: ClassVar[str] = "finishing"
    DOC: ClassVar[str] = (
        "the worker is finishing the session (after the last queued frame): sent when it "
        "starts and every 2 s until `finished`"
    )
    elapsed_s: float = info(doc="since finish began")
    phase: Literal["mapping", "loop_closing", "refining", "done"] | None = info(
        doc=(
            "mapping: the keyframes still waiting are mapped; loop_closing: the last loop "
            "queries are answered; refining: the final refinement"
        ),
        default=None,
    )
    done: int | None = info(doc="work units of the phase done (keyframes, iterations)", default=None)
    total: int | None = info(doc="work units of the phase in all", default=None)
    eta_s: float | None = info(
        doc=(
            "seconds the phase still needs at its pace so far (bounded by the finish "
            "budget); absent until there is a pace"
        ),
        default=None,
    )


@dataclass(frozen=True, kw_only=True)
class FinishedMessage(ServerMessage):
    TYPE: ClassVar[str] = "finished"
    frames: int = info(doc="frames processed")


@dataclass(frozen=True, kw_only=True)
class PongMessage(ServerMessage):
    TYPE: ClassVar[str] = "pong"


CLIENT_MESSAGES: dict[str, type[ClientMessage]] = {
    FrameMessage.TYPE: FrameMessage,
    FinishMessage.TYPE: FinishMessage,
    PingMessage.TYPE: PingMessage,
}
SERVER_MESSAGES: dict[str, type[ServerMessage]] = {
    AckMessage.TYPE: AckMessage,
    PoseMessage.TYPE: PoseMessage,
    SkippedMessage.TYPE: SkippedMessage,
    LoopClosed.TYPE: LoopClosed,
    TrackingLost.TYPE: TrackingLost,
    Relocalized.TYPE: Relocalized,
    Initializing.TYPE: Initializing,
    Initialized.TYPE: Initialized,
    NewMap.TYPE: NewMap,
    RotationOnly.TYPE: RotationOnly,
    MapsMerged.TYPE: MapsMerged,
    DriftCorrected.TYPE: DriftCorrected,
    PosesRefined.TYPE: PosesRefined,
    DevicePoseJump.TYPE: DevicePoseJump,
    PoseSourceChosen.TYPE: PoseSourceChosen,
    OdometrySlip.TYPE: OdometrySlip,
    DepthMisregistered.TYPE: DepthMisregistered,
    MapExtended.TYPE: MapExtended,
    MapNotExtended.TYPE: MapNotExtended,
    ErrorMessage.TYPE: ErrorMessage,
    FinishingMessage.TYPE: FinishingMessage,
    FinishedMessage.TYPE: FinishedMessage,
    PongMessage.TYPE: PongMessage,
}
# The engine's events by what they tell: the pose source's state, ...
TRACKING_EVENTS: tuple[type[ServerMessage], ...] = (TrackingLost, Relocalized, Initialized, Initializing, NewMap,
                                                     RotationOnly)
# ... notices about the input (tracking goes on), ...
INPUT_EVENTS: tuple[type[ServerMessage], ...] = (DevicePoseJump, OdometrySlip, DepthMisregistered, PoseSourceChosen)
# ... and corrections of the map's past, each with the trajectory revision it made (a loop closure aside)
MAP_EVENTS: tuple[type[ServerMessage], ...] = (MapsMerged, DriftCorrected, PosesRefined)


def parse_server_message(data: dict[str, Any]) -> ServerMessage | None:
    """The typed message for a decoded server message; None for a type this version does not know, ValueError for
    one without a field its type requires."""
    kind = SERVER_MESSAGES.get(data.get("type"))  # type: ignore[arg-type]
    return kind.from_dict(data) if kind is not None else None  # type: ignore[return-value]
