"""WebSocket streaming against the real stack: the happy path, every kind of bad input, isolation of sessions."""

from __future__ import annotations

import json

import cv2
import msgpack
import numpy as np
import pytest
from conftest import MAX_FRAME_BYTES, OTHER_STREAM_KEY, STREAM_KEY
from service_helpers import ICL_INTRINSICS, frame_message, icl_frames, of_type, receive_until
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

FRAMES = icl_frames(8)


def ws_url(stack, session_id: str, key: str | None = STREAM_KEY, header: bool = True) -> tuple[str, dict]:
    url = f"{stack.ws_url}/v1/sessions/{session_id}/stream"
    if key and not header:
        return f"{url}?api_key={key}", {}
    return url, ({"X-API-Key": key} if key else {})


def open_stream(stack, session_id: str, key: str | None = STREAM_KEY, header: bool = True):
    url, headers = ws_url(stack, session_id, key, header)
    return connect(url, additional_headers=headers, open_timeout=20)


def send_and_expect(ws, payload, kind: str, seq: int | None = None, log: list | None = None) -> dict:
    """Send a frame and return the gateway's answer to it (other messages go to `log`)."""
    ws.send(payload)
    messages = receive_until(ws, lambda m: m["type"] == "ack" or (m["type"] == "error" and m.get("seq") in (None, seq)),
                             timeout_s=20)
    if log is not None:
        log += messages[:-1]
    return messages[-1] | {"_expected": kind}


def finish(ws) -> list[dict]:
    ws.send(json.dumps({"type": "finish"}))
    return receive_until(ws, lambda m: m["type"] == "finished", timeout_s=30)


def test_stream_poses_ack_and_finish(api, stack):
    sid = api.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS}).json()["id"]
    with open_stream(stack, sid) as ws:
        for seq, frame in enumerate(FRAMES):
            ws.send(frame_message(seq, frame, with_pose=True))
        messages = finish(ws)
        with pytest.raises(ConnectionClosed):  # the server closes after "finished"
            ws.recv(timeout=10)
    acks = of_type(messages, "ack")
    assert [a["seq"] for a in acks] == list(range(len(FRAMES)))
    assert all(1 <= a["queue_depth"] <= len(FRAMES) for a in acks)
    poses = of_type(messages, "pose")
    assert [p["seq"] for p in poses] == list(range(len(FRAMES)))
    for pose, frame in zip(poses, FRAMES):  # the passthrough engine reports the frame's own pose prior
        assert pose["pose"] == pytest.approx(frame["pose"]) and pose["timestamp"] == frame["timestamp"]
    assert messages[-1] == {"type": "finished", "frames": len(FRAMES)}
    session = api.get(f"/v1/sessions/{sid}").json()
    assert session["status"] == "finished"
    assert session["frames_received"] == session["frames_processed"] == len(FRAMES)
    traj = api.get(f"/v1/sessions/{sid}/trajectory").json()
    assert [p["seq"] for p in traj["poses"]] == list(range(len(FRAMES)))
    keyframes = api.get(f"/v1/sessions/{sid}/trajectory", params={"which": "keyframes"}).json()["poses"]
    assert [p["seq"] for p in keyframes] == [p["seq"] for p in poses if p["is_keyframe"]]
    tum = api.get(f"/v1/sessions/{sid}/trajectory", params={"format": "tum"})
    assert tum.headers["content-type"].startswith("text/plain")
    rows = [line.split() for line in tum.text.splitlines() if not line.startswith("#")]
    assert len(rows) == len(FRAMES)
    assert [float(v) for v in rows[3][1:4]] == pytest.approx([FRAMES[3]["pose"][i] for i in (3, 7, 11)], abs=1e-6)
    with open_stream(stack, sid) as ws:  # a finished session takes no more frames
        message = json.loads(ws.recv(timeout=10))
        assert message["code"] == "not_accepting"


def test_bad_inputs_get_clear_errors_and_the_session_goes_on(api, stack):
    sid = api.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS}).json()["id"]
    bystander = api.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS}).json()["id"]
    good = FRAMES[0]
    truncated = good["jpeg"][: len(good["jpeg"]) // 2]  # a valid header, the pixels cut off: the worker notices
    with open_stream(stack, sid) as ws, open_stream(stack, bystander, header=False) as other:
        assert send_and_expect(ws, frame_message(0, good), "ack")["type"] == "ack"
        other.send(frame_message(0, good))
        cases = [
            (b"\x93\x01\x02", "bad_message"),  # msgpack, but not a map
            (b"\xc1\xff\x00garbage", "bad_message"),  # not msgpack
            (msgpack.packb({"type": "frame", "seq": 1, "timestamp": 0.1, "image": b"\xff\xd8\xff" + b"\0" * 64}),
             "bad_image"),
            (msgpack.packb({"type": "frame", "seq": 1, "timestamp": 0.1, "image": b"GIF89a...."}), "bad_image"),
            (frame_message(1, good, intrinsics={"fx": -5, "fy": 262.5, "cx": 160, "cy": 120}), "bad_intrinsics"),
            (frame_message(1, good, intrinsics=[262.5, 262.5, 900.0, 120.0]), "bad_intrinsics"),
            (frame_message(1, good, intrinsics={"fx": 262.5}), "bad_intrinsics"),
            (frame_message(1, good, pose=[1.0] * 15), "bad_pose"),
            (frame_message(1, good, depth=cv2.imencode(".png", np.zeros((120, 160), np.uint16))[1].tobytes()),
             "bad_depth"),  # depth of another size than the image
            (frame_message(1, good, depth=good["jpeg"]), "bad_depth"),
            (frame_message(1, good, padding=b"\0" * MAX_FRAME_BYTES), "too_large"),
            (frame_message(0, good), "bad_seq"),  # duplicate
            (msgpack.packb({"type": "frame", "seq": "one", "timestamp": 0.1, "image": good["jpeg"]}),
             "bad_message"),
        ]
        for payload, code in cases:
            reply = send_and_expect(ws, payload, code, seq=_seq_of(payload))
            assert reply["type"] == "error" and reply["code"] == code, (code, reply)
            assert reply["message"]
        ws.send("this is not json")
        assert receive_until(ws, lambda m: m["type"] == "error")[-1]["code"] == "bad_message"
        ws.send(json.dumps({"type": "dance"}))
        assert "unknown control" in receive_until(ws, lambda m: m["type"] == "error")[-1]["message"]
        ws.send(json.dumps({"type": "ping"}))
        assert receive_until(ws, lambda m: m["type"] == "pong")
        # seq 1 is still free: none of the refused frames consumed it
        log: list[dict] = []
        assert send_and_expect(ws, frame_message(1, FRAMES[1]), "ack", 1, log)["seq"] == 1
        assert send_and_expect(ws, frame_message(3, FRAMES[3], intrinsics=[262.5, 262.5, 159.75, 119.75]),
                               "ack", 3, log)["seq"] == 3
        reply = send_and_expect(ws, frame_message(2, FRAMES[2]), "bad_seq", 2, log)  # out of order
        assert reply["code"] == "bad_seq" and "not greater" in reply["message"]
        assert send_and_expect(ws, frame_message(4, good, image=truncated), "ack", 4, log)["type"] == "ack"
        assert send_and_expect(ws, frame_message(5, FRAMES[5]), "ack", 5, log)["seq"] == 5
        messages = log + finish(ws)
        worker_error = [m for m in messages if m["type"] == "error"]
        assert [(m["code"], m["seq"]) for m in worker_error] == [("bad_image", 4)]
        assert "image" in worker_error[0]["message"]
        other.send(frame_message(1, FRAMES[1]))
        other_messages = finish(other)
        assert {p["seq"] for p in of_type(other_messages, "pose")} >= {1}
    session = api.get(f"/v1/sessions/{sid}").json()
    assert session["status"] == "finished"
    assert (session["frames_received"], session["frames_processed"], session["frames_rejected"]) == (5, 4, 1)
    assert [p["seq"] for p in api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]] == [0, 1, 3, 5]
    assert api.get(f"/v1/sessions/{bystander}").json()["frames_processed"] == 2


def _seq_of(payload: bytes):
    try:
        seq = msgpack.unpackb(payload).get("seq")
    except Exception:
        return None
    return seq if isinstance(seq, int) else None


def test_session_intrinsics_with_another_aspect_ratio_are_refused(api, stack):
    square = {"fx": 100.0, "fy": 100.0, "cx": 50.0, "cy": 50.0, "width": 100, "height": 100}
    sid = api.post("/v1/sessions", json={"intrinsics": square}).json()["id"]
    with open_stream(stack, sid) as ws:
        reply = send_and_expect(ws, frame_message(0, FRAMES[0]), "bad_intrinsics", 0)
        assert reply["code"] == "bad_intrinsics" and "320x240" in reply["message"]


@pytest.mark.parametrize("key, code, close_code", [(None, "unauthorized", 4401), ("wrong", "unauthorized", 4401),
                                                   (OTHER_STREAM_KEY, "forbidden", 4403)])
def test_stream_auth_errors(api, stack, key, code, close_code):
    sid = api.post("/v1/sessions", json={}).json()["id"]
    with open_stream(stack, sid, key=key) as ws:
        assert json.loads(ws.recv(timeout=10))["code"] == code
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
    assert closed.value.rcvd.code == close_code


def test_unknown_session_stream_is_not_found(stack):
    with open_stream(stack, "no-such-session") as ws:
        message = json.loads(ws.recv(timeout=10))
        assert message["code"] == "not_found" and "not found" in message["message"]
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
    assert closed.value.rcvd.code == 4404
