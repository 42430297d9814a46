"""The engine's typed events (worker.events): on the wire they are the protocol messages, field for field what the
engine sent when its events were dicts (the scalars of the dict, stamped with the seq, or the revision of a loop
closure); in snapshots they keep the dict form older snapshots hold, and such dicts load."""

from __future__ import annotations

import json
import types
import typing
from dataclasses import fields
from typing import Any, get_args, get_origin, get_type_hints

import numpy as np
import pytest

from protocol.messages import SERVER_MESSAGES, LoopClosed
from worker.events import ENGINE_EVENTS, WIRE_SCALARS, EngineEvent, Initialized, MapsMerged, event_from_dict
from worker.pipeline.loop_stage import MapJoin, item_state
from worker.runtime.sessions import SessionRunner

IDENTITY = np.eye(4).tolist()
# Event dicts as the engine made them before its events were typed (after the pipeline added what it adds: a
# revision, the pose-graph errors, a verdict's replayed frames), one per place that makes them.
OLD_EVENTS = [
    {"type": "tracking_lost", "reason": "too few map points tracked", "frame": 4},
    {"type": "tracking_lost", "reason": "no depth in the first frame"},
    {"type": "relocalized", "method": "device_pose", "reason": "lost for 1.0 s"},
    {"type": "relocalized", "keyframe": 3},
    {"type": "relocalized", "frame": 9, "place": 5, "inliers": 80, "lost_frames": 2},
    {"type": "relocalized", "frame": 9, "place": 5, "inliers": 80, "method": "learned glue", "lost_frames": 2},
    {"type": "relocalized", "frame": 9, "method": "reinitialized", "place": 4, "inliers": 120, "model": "essential",
     "scale_from": "shared points", "shared_points": 30, "lost_frames": 3},
    {"type": "relocalized", "frame": 9, "method": "device"},
    {"type": "relocalized", "map_id": "map1", "frame": 3, "keyframe": 8, "inliers": 120, "matches": 200,
     "reprojection_px": 0.8, "depth_agreement": 0.9, "revision": 2},
    {"type": "initializing", "frame": 1, "state": "rotation_only", "reason": "no parallax", "model": "homography",
     "score_ratio": 0.912},
    {"type": "initialized", "frame": 7, "map": 1, "points": 200, "parallax_deg": 2.5, "model": "essential",
     "score_ratio": 0.3, "intrinsics": {"fx": 400.0, "fy": 400.0, "cx": 160.0, "cy": 120.0, "width": 320,
                                        "height": 240}, "revision": 2, "frames_revised": 6},
    {"type": "initialized", "frame": 30, "map": 2, "points": 150, "parallax_deg": 3.1, "model": "essential",
     "score_ratio": 0.2, "revision": 4, "frames_revised": 3, "registered_frames": [27, 28, 29]},
    {"type": "initialized", "frames": [[0, IDENTITY]], "intrinsics": {"fx": 500.0}, "focal_trusted": True},
    {"type": "new_map", "frame": 22, "map": 2, "lost_frames": 2, "scene_depth": 1.5},
    {"type": "rotation_only", "frame": 5, "tracks": 40, "map_points": 12},
    {"type": "rotation_only", "frame": 5, "method": "photometric", "tracks": 0, "map_points": 0,
     "correlation": 0.8, "measured_axes": 2},
    {"type": "maps_merged", "frame": 30, "place": 3, "since": 20, "scale": 1.2, "pairs": 40, "spread": 0.3,
     "method": "orb", "relative": IDENTITY, "correction": IDENTITY},
    {"frame": 30, "place": 3, "since": 20, "scale": 1.2, "pairs": 40, "spread": 0.3, "method": "learned",
     "type": "maps_merged", "from_keyframe": 30, "to_keyframe": 3, "pgo_error_before": 1.5,
     "pgo_error_after": 0.1, "revision": 5},
    {"type": "drift_corrected", "keyframe": 12, "pgo_error_before": 2.0, "pgo_error_after": 0.2, "revision": 3},
    {"type": "drift_corrected", "keyframe": 12, "source": "map", "pgo_error_before": 2.0, "pgo_error_after": 0.2,
     "revision": 3},
    {"type": "poses_refined", "keyframes": 2, "revision": 7},
    {"type": "device_pose_jump", "frame": 5, "translation": 0.3, "rotation_deg": 4.0,
     "action": "prior dropped, device re-anchored"},
    {"type": "odometry_slip", "frame": 5, "photometric_rms": [0.1, 0.05], "geometric_rms": [0.01, 0.005],
     "action": "re-tracked from the device's motion"},
    {"type": "depth_misregistered", "shift_px": [3, 0], "shift_dx": 3, "shift_dy": 0, "agreement": 0.5,
     "agreement_unshifted": 0.3, "message": "colour and depth are not registered"},
    {"type": "pose_source_chosen", "frame": 20, "pose_source": "seeded", "reason": "device poses disagree",
     "reprojection_px": 2.0, "fitted_px": 0.5, "ratio": 4.0, "max_ratio": 2.0, "triples": 60, "agree": False,
     "frames_replayed": 21, "revision": 1},
    {"type": "map_extended", "map_id": "m1", "version": 3, "keyframes": 40},
    {"type": "map_not_extended", "map_id": "m1", "reason": "the map was deleted"},
    {"type": "loop_closed", "from_keyframe": 40, "to_keyframe": 2, "source": "pnp", "scale": 1.0,
     "also_to_keyframes": [3], "pgo_error_before": 2.0, "pgo_error_after": 0.1, "revision": 3},
]


def _scalars(event: dict[str, Any]) -> dict[str, Any]:
    """What the runtime published of an event dict: its scalar fields."""
    return {k: v for k, v in event.items() if isinstance(v, (int, float, str, bool))}


@pytest.mark.parametrize("old", OLD_EVENTS, ids=[f"{e['type']}-{n}" for n, e in enumerate(OLD_EVENTS)])
def test_each_event_keeps_its_wire_form_and_its_snapshot_form(old):
    event = event_from_dict(old)
    assert type(event) is ENGINE_EVENTS[old["type"]] and event.to_dict() == old  # nothing lost, same dict
    if isinstance(event, LoopClosed):
        wire, expected = event.to_message(revision=9, seq=44), {**_scalars(old), "type": "loop_closed", "revision": 9}
    else:
        wire, expected = event.to_message(seq=44), {**_scalars(old), "seq": 44}
    assert type(wire) is SERVER_MESSAGES[old["type"]]
    assert json.loads(wire.to_json()) == expected


def _is_scalar(hint: Any) -> bool:
    if get_origin(hint) in (typing.Union, types.UnionType):
        return any(_is_scalar(arg) for arg in get_args(hint) if arg is not type(None))
    return hint in WIRE_SCALARS


@pytest.mark.parametrize("kind", list(ENGINE_EVENTS.values()), ids=list(ENGINE_EVENTS))
def test_what_only_the_engine_keeps_is_never_a_scalar(kind):
    """Every scalar an event carries is a field of its protocol message (documented in openapi.yaml); the engine's
    own fields are lists and dicts, which the wire never carried."""
    message = SERVER_MESSAGES[kind.TYPE]
    assert issubclass(kind, message) and issubclass(kind, EngineEvent)
    declared = {item.name for item in fields(message)}
    own = {item.name: get_type_hints(kind)[item.name] for item in fields(kind)}
    assert all(not _is_scalar(hint) for name, hint in own.items() if name not in declared | {"seq"})


def test_fields_are_checked():
    with pytest.raises(TypeError):
        Initialized(frame=1, revison=2)  # type: ignore[call-arg]


def test_older_snapshots_loop_stage_events_load():
    """A loop stage's snapshot holds its corrections' events and its queued map joins' as dicts: older snapshots'
    dicts load as typed events, and a new snapshot writes the same dicts."""
    old = next(e for e in OLD_EVENTS if e["type"] == "maps_merged" and "relative" in e)
    join = MapJoin(3, 30, np.eye(4), event_from_dict(old))
    assert isinstance(join.event, MapsMerged) and join.event.relative == IDENTITY
    assert item_state(join)["event"] == old


class _Outbox:
    """A Redis client's xadd, recorded."""

    def __init__(self) -> None:
        self.messages: list[dict[str, Any]] = []

    def xadd(self, _stream, fields, **_options) -> None:
        self.messages.append(json.loads(fields["msg"]))


def _runner(revision: int = 0) -> SessionRunner:
    runner = object.__new__(SessionRunner)  # the publishing part of a runner, without its threads and Redis
    runner.client, runner.session_id, runner._revision = _Outbox(), "s", revision
    runner.config = types.SimpleNamespace(outbox_maxlen=100)
    runner._store_trajectory = lambda: None
    return runner


def test_the_runtime_publishes_the_protocol_messages():
    runner = _runner()
    lost = event_from_dict(OLD_EVENTS[0])
    merged = event_from_dict(next(e for e in OLD_EVENTS if e["type"] == "maps_merged" and "revision" in e))
    runner._publish_event(6, lost)
    runner._publish_revision(5, [merged])  # it carries its revision: no loop closure is made up for it
    runner._publish_revision(6, [])  # a revision without an event of its own: told as a loop closure
    runner._publish_revision(7, [event_from_dict(OLD_EVENTS[-1])])
    assert runner.client.messages == [
        {"type": "tracking_lost", "seq": 6, "reason": "too few map points tracked", "frame": 4},
        {"type": "loop_closed", "revision": 6},
        {**_scalars(OLD_EVENTS[-1]), "revision": 7}]
