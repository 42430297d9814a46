"""The typed WebSocket messages: their wire form, their parsing, and the schema openapi.yaml is generated from."""

from __future__ import annotations

import json
from typing import get_args

import numpy as np
import pytest

from protocol.codec import unpack
from protocol.messages import (
    CLIENT_MESSAGES,
    ERROR_CODES,
    SERVER_MESSAGES,
    ErrorCode,
    ErrorMessage,
    FinishedMessage,
    FrameMessage,
    PoseMessage,
    TrackingLost,
    parse_server_message,
)
from protocol.schema import message_schema
from service.websocket_doc import WEBSOCKET_DOC


def test_wire_form_puts_type_first_and_leaves_unset_fields_out():
    text = ErrorMessage(code="bad_seq", message="seq 3 is not above 4", seq=3).to_json()
    assert json.loads(text) == {"type": "error", "code": "bad_seq", "message": "seq 3 is not above 4", "seq": 3}
    # the gateway recognises the end of a stream by this prefix (service.routes_stream)
    assert FinishedMessage(frames=7).to_json().startswith('{"type": "finished"')


def test_server_messages_parse_back_and_unknown_types_are_none():
    pose = PoseMessage(seq=1, timestamp=0.5, pose=np.eye(4).reshape(-1).tolist(), scale=1.0, is_keyframe=True,
                       revision=2)
    assert parse_server_message(json.loads(pose.to_json())) == pose
    lost = parse_server_message({"type": "tracking_lost", "seq": 4, "reason": "blur", "engine_detail": 1})
    assert lost == TrackingLost(seq=4, reason="blur")  # fields the engine adds pass by, undeclared
    assert parse_server_message({"type": "from_the_future"}) is None
    with pytest.raises(ValueError, match="a pose message without timestamp, pose"):
        parse_server_message({"type": "pose", "seq": 1, "scale": 1.0, "is_keyframe": False, "revision": 0})


def test_frame_message_encodes_as_msgpack():
    message = FrameMessage(seq=0, timestamp=1.5, image=b"\xff\xd8", pose=[1.0] * 16)
    assert unpack(message.encode()) == {"type": "frame", "seq": 0, "timestamp": 1.5, "image": b"\xff\xd8",
                                        "pose": [1.0] * 16}


def test_schema_is_derived_from_the_classes():
    stream = WEBSOCKET_DOC["/v1/sessions/{session_id}/stream"]
    assert set(stream["client_messages"]) == set(CLIENT_MESSAGES)
    assert set(stream["server_messages"]) - {"encoding"} == set(SERVER_MESSAGES)
    pose = message_schema(PoseMessage)
    assert pose["required"] == ["type", "seq", "timestamp", "pose", "scale", "is_keyframe", "revision"]
    assert pose["properties"]["pose"]["minItems"] == 16 and pose["properties"]["type"] == {"const": "pose"}
    error = stream["server_messages"]["error"]
    assert error["properties"]["code"]["enum"] == list(ERROR_CODES) == list(get_args(ErrorCode))
    assert message_schema(TrackingLost)["additionalProperties"] is True


def test_every_message_type_is_unique():
    types = [kind.TYPE for kind in (*CLIENT_MESSAGES.values(), *SERVER_MESSAGES.values())]
    assert len(types) == len(set(types))
    with pytest.raises(TypeError):
        ErrorMessage(message="no code")  # type: ignore[call-arg]
