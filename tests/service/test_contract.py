"""Small points of the client contract, against the real stack: one 422 body shape; a frame sent as text JSON is
told to be binary msgpack; a frame of another size than the session's first is refused at the gateway."""

from __future__ import annotations

import json

from conftest import STREAM_KEY
from service_helpers import frame_message, icl_frames, receive_until
from websockets.sync.client import connect

FRAMES = icl_frames(3)
HALF = icl_frames(1, scale=0.5)[0]


def _stream(stack, session_id: str):
    return connect(f"{stack.ws_url}/v1/sessions/{session_id}/stream", additional_headers={"X-API-Key": STREAM_KEY},
                   open_timeout=20)


def _answer(ws, payload) -> dict:
    ws.send(payload)
    return receive_until(ws, lambda m: m["type"] in ("ack", "error"), timeout_s=20)[-1]


def test_every_422_has_the_same_body_shape(api):
    unknown_preset = api.post("/v1/sessions", json={"preset": "no-such-preset"})
    bad_field = api.post("/v1/sessions", json={"intrinsics": {"fx": -1, "fy": 1, "cx": 1, "cy": 1, "width": 4,
                                                              "height": 4}})
    bad_query = api.get("/v1/sessions", params={"limit": 0})
    for response in (unknown_preset, bad_field, bad_query):
        assert response.status_code == 422
        detail = response.json()["detail"]
        assert isinstance(detail, list) and detail
        assert all({"loc", "msg", "type"} <= set(item) for item in detail), detail
    assert unknown_preset.json()["detail"][0]["loc"] == ["body", "preset"]
    assert unknown_preset.json()["detail"][0]["input"] == "no-such-preset"
    assert "rgbd" in unknown_preset.json()["detail"][0]["msg"]  # names the valid presets


def test_a_frame_sent_as_text_json_is_told_to_be_binary_msgpack(api, stack):
    sid = api.post("/v1/sessions", json={}).json()["id"]
    with _stream(stack, sid) as ws:
        reply = _answer(ws, json.dumps({"type": "frame", "seq": 0, "timestamp": 0.0, "image": "aGVsbG8="}))
        assert reply["code"] == "bad_message" and reply["seq"] == 0
        assert "binary" in reply["message"] and "msgpack" in reply["message"]
        reply = _answer(ws, "not json at all")
        assert reply["code"] == "bad_message" and "binary" in reply["message"]
        assert _answer(ws, frame_message(0, FRAMES[0]))["type"] == "ack"  # the stream goes on


def test_a_frame_of_another_size_is_refused_at_the_gateway(api, stack):
    sid = api.post("/v1/sessions", json={}).json()["id"]  # no intrinsics: the first frame sets the size
    with _stream(stack, sid) as ws:
        assert _answer(ws, frame_message(0, FRAMES[0]))["type"] == "ack"
        reply = _answer(ws, frame_message(1, HALF))
        assert (reply["type"], reply["code"], reply["seq"]) == ("error", "bad_size", 1)
        assert "160x120" in reply["message"] and "320x240" in reply["message"]
        assert _answer(ws, frame_message(2, FRAMES[2]))["type"] == "ack"
    session = api.get(f"/v1/sessions/{sid}").json()
    assert session["frames_received"] == 2  # the refused frame was never queued



def test_map_sh_degree_is_validated_and_passed_on(api, stack):
    sid = api.post("/v1/sessions", json={}).json()["id"]
    with _stream(stack, sid) as ws:
        assert _answer(ws, frame_message(0, FRAMES[0]))["type"] == "ack"
        ws.send('{"type": "finish"}')
        receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
    assert api.get(f"/v1/sessions/{sid}/map.ply", params={"sh_degree": 4}).status_code == 422
    for degree in (0, 3):  # the passthrough engine's point PLY has no f_dc: served as it is
        response = api.get(f"/v1/sessions/{sid}/map.ply", params={"sh_degree": degree})
        assert response.status_code == 200 and response.content.startswith(b"ply\n")
