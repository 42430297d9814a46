"""The WebSocket contract in openapi.yaml is complete: every error and close code the code can send is documented,
every close is preceded by an error message, and poses carry their similarity scale so a client recovers the
right rotation."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import STREAM_KEY
from service_helpers import frame_message, icl_frames, receive_until
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from protocol.messages import CLOSE_CODES
from protocol.messages import ERROR_CODES as FRAME_ERROR_CODES
from worker.geometry import rotmat_to_quat

ROOT = Path(__file__).resolve().parents[2]
SOURCES = [ROOT / "service" / "routes_stream.py", ROOT / "service" / "frame_validation.py",
           *sorted((ROOT / "worker" / "runtime").glob("*.py"))]
FRAMES = icl_frames(2)


def test_every_error_code_the_code_sends_is_documented():
    patterns = (r'code="([a-z_]+)"', r'error\(\s*"([a-z_]+)"', r'FrameRejected\(\s*"([a-z_]+)"',
                r'FrameError\(\s*"([a-z_]+)"', r'_reject\([^)]*?"([a-z_]+)"', r'"code": "([a-z_]+)"')
    sent = {code for path in SOURCES for pattern in patterns for code in re.findall(pattern, path.read_text())}
    sent -= {"error"}  # the generic fallback of _AUTH_CODES
    assert sent and sent <= set(FRAME_ERROR_CODES), sorted(sent - set(FRAME_ERROR_CODES))


def test_every_close_code_the_gateway_uses_is_documented():
    text = (ROOT / "service" / "routes_stream.py").read_text()
    used = set(re.findall(r"close\(code=(\d{4})[,)]", text)) | set(re.findall(r"_close\((\d{4})\)", text))
    used |= {str(4000 + status) for status in (401, 403, 404)}  # 4000 + the HTTP status of an auth failure
    assert used <= set(CLOSE_CODES), sorted(used - set(CLOSE_CODES))


def _closed_after_error(url: str, headers: dict | None = None) -> tuple[dict, int]:
    with connect(url, additional_headers=headers or {}, open_timeout=20) as ws:
        message = json.loads(ws.recv(timeout=10))
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
    return message, closed.value.rcvd.code


def test_bad_query_key_and_finished_session_close_after_an_error_message(api, stack):
    sid = api.post("/v1/sessions", json={}).json()["id"]
    message, code = _closed_after_error(f"{stack.ws_url}/v1/sessions/{sid}/stream?api_key=wrong")
    assert (message["type"], message["code"], code) == ("error", "unauthorized", 4401) and message["message"]
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", additional_headers={"X-API-Key": STREAM_KEY},
                 open_timeout=20) as ws:
        ws.send('{"type": "finish"}')
        ending = [m["type"] for m in receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)]
    assert ending[-2:] == ["finishing", "finished"]  # progress while the worker finishes
    message, code = _closed_after_error(f"{stack.ws_url}/v1/sessions/{sid}/stream",
                                        {"X-API-Key": STREAM_KEY})
    assert (message["type"], message["code"], code) == ("error", "not_accepting", 4409) and message["message"]


def test_poses_carry_the_similarity_scale(api, stack):
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = 2.5 * rotation
    pose[:3, 3] = [0.1, 0.2, 0.3]
    sid = api.post("/v1/sessions", json={}).json()["id"]
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", additional_headers={"X-API-Key": STREAM_KEY},
                 open_timeout=20) as ws:
        ws.send(frame_message(0, {**FRAMES[0], "pose": pose.reshape(-1).tolist()}, with_pose=True))
        ws.send('{"type": "finish"}')
        live = [m for m in receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60) if m["type"] == "pose"]
    stored = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
    for message in (live[0], stored[0]):
        assert message["scale"] == pytest.approx(2.5)
        block = np.asarray(message["pose"]).reshape(4, 4)[:3, :3] / message["scale"]
        assert np.allclose(block @ block.T, np.eye(3)) and np.allclose(block, rotation)
        quaternion = rotmat_to_quat(torch.from_numpy(block)).tolist()  # what a client would do, wxyz
        assert quaternion == pytest.approx([np.cos(angle / 2), 0, 0, np.sin(angle / 2)], abs=1e-9)
