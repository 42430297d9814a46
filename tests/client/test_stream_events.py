"""The SDK's stream events are parsed by the protocol's typed messages (`protocol.messages.parse_server_message`):
each carries its typed message, `data` keeps the message as it came (fields this SDK does not know included), and
the stream hands them to its summary and callback as before."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from client.async_sdk import AsyncFrameStream
from client.models import (
    INPUT_EVENT_TYPES,
    TRACKING_EVENT_TYPES,
    InputEvent,
    LoopClosedEvent,
    PoseEvent,
    TrackingEvent,
    event_from_message,
)
from protocol.messages import LoopClosed, PoseMessage, PoseSourceChosen, Relocalized, TrackingLost

POSE = {"type": "pose", "seq": 3, "timestamp": 0.1, "pose": np.eye(4).reshape(-1).tolist(), "scale": 2.0,
        "is_keyframe": True, "revision": 1}


def test_a_pose_is_a_pose_event_with_its_typed_message():
    event = event_from_message(POSE)
    assert isinstance(event, PoseEvent) and isinstance(event.message, PoseMessage)
    assert (event.seq, event.timestamp, event.is_keyframe, event.revision, event.scale) == (3, 0.1, True, 1, 2.0)
    np.testing.assert_array_equal(event.pose, np.eye(4))


def test_engine_events_keep_every_field_and_their_typed_message():
    message = {"type": "relocalized", "seq": 9, "frame": 8, "method": "reinitialized", "inliers": 120,
               "from_a_newer_server": 1}
    event = event_from_message(message)
    assert isinstance(event, TrackingEvent) and (event.kind, event.seq) == ("relocalized", 9)
    assert event.data == message  # what this SDK does not know too
    assert event.message == Relocalized(seq=9, frame=8, method="reinitialized", inliers=120)
    lost = event_from_message({"type": "tracking_lost", "seq": 4, "reason": "blur"})
    assert isinstance(lost, TrackingEvent) and lost.message == TrackingLost(seq=4, reason="blur")
    chosen = event_from_message({"type": "pose_source_chosen", "seq": 20, "pose_source": "seeded", "revision": 2})
    assert isinstance(chosen, InputEvent) and isinstance(chosen.message, PoseSourceChosen)
    assert chosen.message.pose_source == "seeded" and chosen.data["revision"] == 2
    loop = event_from_message({"type": "loop_closed", "revision": 5, "from_keyframe": 40, "to_keyframe": 2})
    assert isinstance(loop, LoopClosedEvent) and loop.revision == 5
    assert loop.message == LoopClosed(revision=5, from_keyframe=40, to_keyframe=2)


def test_the_event_kinds_are_the_protocols():
    assert set(TRACKING_EVENT_TYPES) == {"tracking_lost", "relocalized", "initialized", "initializing", "new_map",
                                         "maps_merged", "drift_corrected", "poses_refined", "rotation_only"}
    assert set(INPUT_EVENT_TYPES) == {"pose_source_chosen", "device_pose_jump", "odometry_slip",
                                      "depth_misregistered"}


def test_other_messages_are_no_event_and_a_malformed_one_is_refused():
    assert event_from_message({"type": "ack", "seq": 1, "queue_depth": 2}) is None
    assert event_from_message({"type": "from_the_future", "seq": 1}) is None
    with pytest.raises(ValueError, match="without seq"):
        event_from_message({"type": "tracking_lost", "reason": "blur"})


def test_the_stream_sorts_what_it_receives():
    seen = []
    stream = AsyncFrameStream("ws://unused", "s", {}, on_event=seen.append)

    async def receive() -> None:
        for message in (POSE, POSE, {"type": "tracking_lost", "seq": 4, "reason": "blur"},
                        {"type": "device_pose_jump", "seq": 5, "translation": 0.3},
                        {"type": "loop_closed", "revision": 2}, {"type": "skipped", "seq": 6, "reason": "overload"},
                        {"type": "finishing", "elapsed_s": 0.0}, {"type": "finished", "frames": 7}):
            await stream._handle(json.dumps(message))

    asyncio.run(receive())
    summary = stream.summary
    assert [e.seq for e in summary.poses] == [3]  # a result reported twice is reported once
    assert [(e.kind, e.seq) for e in summary.tracking_events] == [("tracking_lost", 4)]
    assert [(e.kind, e.data["translation"]) for e in summary.input_events] == [("device_pose_jump", 0.3)]
    assert [e.revision for e in summary.loop_closures] == [2]
    assert summary.skipped == [6] and summary.finished_frames == 7
    assert [type(e).__name__ for e in seen] == ["PoseEvent", "TrackingEvent", "InputEvent", "LoopClosedEvent"]
