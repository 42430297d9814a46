"""The engine's events, typed: one class per event, each its WebSocket message of `protocol.messages` (the fields
clients get, checked by the dataclass) plus what only the engine uses.

Pose sources, the loop-closing stage and finish make them where they happen; the engine passes them on in
`FrameResult.events` (and `finish_events`), and the session runtime sends `event.to_message(seq=...)`: the
protocol class built from the event's fields, stamped with the seq of the frame whose result carried it. What the engine
keeps beside the wire fields (the re-estimated poses of `initialized`, the Sim(3) edge of `maps_merged`, ...) are
the subclasses' own fields, never sent. Until the runtime stamps it an event has no `seq` (a loop closure's has no
revision either until the trajectory gives it one).

In a snapshot an event is its dict, `to_dict()` (`type` and every field set), the form older snapshots hold;
`event_from_dict` reads it back.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from protocol import messages
from protocol.messages import SERVER_MESSAGES, ServerMessage

# What a published event's fields may be: the engine's lists and dicts stay in the engine.
WIRE_SCALARS = (int, float, str, bool)


@dataclass(frozen=True, kw_only=True)
class EngineEvent(ServerMessage):
    """An event as the engine makes it: its protocol message's fields, `seq` unset until the runtime stamps it.
    Subclasses are dataclasses like their messages (frozen, keyword-only) without saying so."""

    seq: int | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        dataclass(frozen=True, kw_only=True)(cls)

    def to_message(self, **stamp: Any) -> ServerMessage:
        """The wire message: this event's fields that its protocol class declares, with `stamp` (seq, revision) over
        them where the class has them; fields that are not scalars are left out (the wire carries scalars)."""
        kind = SERVER_MESSAGES[self.TYPE]
        names = [item.name for item in fields(kind)]
        values = {name: getattr(self, name) for name in names} | {k: v for k, v in stamp.items() if k in names}
        return kind(**{k: v for k, v in values.items() if isinstance(v, WIRE_SCALARS)})


class TrackingLost(EngineEvent, messages.TrackingLost):
    """A pose source lost the camera (worker.tracking: visual or RGB-D odometry, device poses)."""


class Relocalized(EngineEvent, messages.Relocalized):
    """A pose source found the camera again: how (`method`), against what (`place`, `keyframe`, `map_id`). frames:
    the poses of frames reported lost that the source has placed since, [[index, 4x4 list]] (photo registration:
    the engine revises the trajectory with them); registered_frames: their indices, once revised."""

    frames: list[list[Any]] | None = None
    registered_frames: list[int] | None = None


class Initializing(EngineEvent, messages.Initializing):
    """Visual odometry waits for parallax to make its map (worker.tracking.vo_initialisation)."""


class Initialized(EngineEvent, messages.Initialized):
    """A first map (or a new map's) was made. frames: the re-estimated poses of the frames initialisation waited
    for, [[index, 4x4 list]] (the engine revises the trajectory with them); intrinsics: the camera estimated
    meanwhile (a dict), when it was; registered_frames: a new map's frames reported lost while it waited, posed
    now."""

    frames: list[list[Any]] | None = None
    intrinsics: dict[str, Any] | None = None
    registered_frames: list[int] | None = None


class NewMap(EngineEvent, messages.NewMap):
    """Visual odometry gave up finding its map and begins another (worker.tracking.vo_recovery)."""


class RotationOnly(EngineEvent, messages.RotationOnly):
    """Visual odometry follows a turn by its rotation alone (worker.tracking.vo_frame_tracking)."""


class LoopClosed(EngineEvent, messages.LoopClosed):
    """The loop-closing stage closed a loop; the trajectory gives it its revision. also_to_keyframes: further older
    keyframes the loop's keyframe was joined to."""

    revision: int | None = None
    also_to_keyframes: list[int] | None = None


class MapsMerged(EngineEvent, messages.MapsMerged):
    """A restarted map recognised an older one (worker.tracking.vo_map_join); the loop-closing stage's solve of the
    join comes back with it. relative: the Sim(3) edge for the pose graph (this frame in the place's frame, 4x4
    list); correction: the similarity that takes the restarted map's output poses into the older map's (4x4 list)."""

    relative: list[list[float]] | None = None
    correction: list[list[float]] | None = None


class DriftCorrected(EngineEvent, messages.DriftCorrected):
    """The loop-closing stage solved the pose graph with the device's priors (seeded sessions)."""


class PosesRefined(EngineEvent, messages.PosesRefined):
    """The final refinement moved the keyframes' cameras (worker.pipeline.finish)."""


class DevicePoseJump(EngineEvent, messages.DevicePoseJump):
    """Seeded tracking left out a device pose that jumped (worker.tracking.seeded)."""


class PoseSourceChosen(EngineEvent, messages.PoseSourceChosen):
    """The device poses were judged against the images (worker.tracking.pose_choice)."""


class OdometrySlip(EngineEvent, messages.OdometrySlip):
    """Seeded tracking found the odometry slipped where the device did not (worker.tracking.seeded)."""


class DepthMisregistered(EngineEvent, messages.DepthMisregistered):
    """Depth edges do not follow colour edges (worker.data.registration). shift_px: the shift as [dx, dy]."""

    shift_px: list[int] | None = None


class MapExtended(EngineEvent, messages.MapExtended):
    """An `extend` session's map became a new version of its saved map (worker.runtime.session_map)."""


class MapNotExtended(EngineEvent, messages.MapNotExtended):
    """An `extend` session's map could not be added to its saved map (worker.runtime.session_map)."""


ENGINE_EVENTS: dict[str, type[EngineEvent]] = {kind.TYPE: kind for kind in (
    TrackingLost, Relocalized, Initializing, Initialized, NewMap, RotationOnly, LoopClosed, MapsMerged,
    DriftCorrected, PosesRefined, DevicePoseJump, PoseSourceChosen, OdometrySlip, DepthMisregistered, MapExtended,
    MapNotExtended)}


def event_from_dict(data: dict[str, Any]) -> EngineEvent:
    """The event of a snapshot's dict (`to_dict()`, or an older snapshot's event dict); keys no field takes are
    dropped. ValueError for a type the engine does not make."""
    kind = ENGINE_EVENTS.get(data.get("type"))  # type: ignore[arg-type]
    if kind is None:
        raise ValueError(f"not an engine event: {data.get('type')!r}")
    return kind.from_dict(data)  # type: ignore[return-value]
