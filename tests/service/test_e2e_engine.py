"""End to end with the real SlamSystem: stream ICL frames over the WebSocket, read the trajectory, render views
(live from the owning worker, then from the snapshot once finished) and export the map."""

from __future__ import annotations

import collections
import io
import json

import cv2
import httpx
import numpy as np
import pytest
from plyfile import PlyData
from service_helpers import ICL_INTRINSICS, frame_message, icl_frames, of_type, receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

FRAMES = 10
SCALE = 0.5  # 160x120
INTRINSICS = {k: (v * SCALE if k in ("fx", "fy", "cx", "cy") else int(v * SCALE)) for k, v in ICL_INTRINSICS.items()}


@pytest.fixture(scope="module")
def engine_stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_LEASE_TTL_MS": "10000", "FLASHMONO_TORCH_THREADS": "2",
           "FLASHMONO_SNAPSHOT_EVERY": "2", "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=env, gateway_env={"FLASHMONO_REQUEST_TIMEOUT_S": "120"}) as stack:
        yield stack


def decode_png(data: bytes, flags: int) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    assert image is not None, "not a PNG"
    return image


def test_stream_icl_trajectory_render_and_export_with_the_real_engine(engine_stack):
    frames = icl_frames(FRAMES, scale=SCALE)
    with httpx.Client(base_url=engine_stack.base_url, timeout=180) as api:
        sid = api.post("/v1/sessions", json={"intrinsics": INTRINSICS, "preset": "test", "name": "icl"}).json()["id"]
        with connect(f"{engine_stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            for seq, frame in enumerate(frames):
                ws.send(frame_message(seq, frame, with_depth=True))  # RGB-D: metric surfels without weights
            messages = receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == FRAMES - 1, timeout_s=240)
            assert not of_type(messages, "error"), of_type(messages, "error")
            live_pose = np.asarray(of_type(messages, "pose")[2]["pose"]).reshape(4, 4)
            pose_param = ",".join(f"{v:.9g}" for v in live_pose.reshape(-1))
            live = api.get(f"/v1/sessions/{sid}/render", params={"pose": pose_param})  # owner renders, live
            assert live.status_code == 200 and live.headers["content-type"] == "image/png"
            assert decode_png(live.content, cv2.IMREAD_UNCHANGED).shape == (120, 160, 3)
            ws.send(json.dumps({"type": "finish"}))
            messages += receive_until(ws, lambda m: m["type"] == "finished", timeout_s=240)
        poses = of_type(messages, "pose")
        assert collections.Counter(p["seq"] for p in poses) == dict.fromkeys(range(FRAMES), 1)
        assert messages[-1] == {"type": "finished", "frames": FRAMES}
        assert all(np.isfinite(p["pose"]).all() for p in poses)
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["status"] == "finished" and session["frames_processed"] == FRAMES
        assert session["keyframes"] >= 1

        trajectory = api.get(f"/v1/sessions/{sid}/trajectory").json()
        assert [p["seq"] for p in trajectory["poses"]] == list(range(FRAMES))
        assert trajectory["revision"] == session["revision"]
        centres = np.array([np.reshape(p["pose"], (4, 4))[:3, 3] for p in trajectory["poses"]])
        assert np.linalg.norm(centres[-1] - centres[0]) > 0  # the camera moved
        keyframes = api.get(f"/v1/sessions/{sid}/trajectory", params={"which": "keyframes"}).json()["poses"]
        assert 1 <= len(keyframes) <= FRAMES and {p["seq"] for p in keyframes} <= set(range(FRAMES))

        first = ",".join(f"{v:.9g}" for v in trajectory["poses"][0]["pose"])
        color = api.get(f"/v1/sessions/{sid}/render", params={"pose": first, "kind": "color"})
        assert color.status_code == 200
        rgb = decode_png(color.content, cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (120, 160, 3) and rgb.dtype == np.uint8  # content depends on the model's weights
        depth = api.get(f"/v1/sessions/{sid}/render", params={"pose": first, "kind": "depth", "width": 80,
                                                             "height": 60})
        depth_mm = decode_png(depth.content, cv2.IMREAD_UNCHANGED)
        assert depth_mm.dtype == np.uint16 and depth_mm.shape == (60, 80)
        bad = api.get(f"/v1/sessions/{sid}/render", params={"pose": "1,2,3"})
        assert bad.status_code == 400 and "16" in bad.json()["detail"]

        ply = api.get(f"/v1/sessions/{sid}/map.ply")
        assert ply.status_code == 200 and ply.headers["content-type"] == "application/octet-stream"
        vertices = PlyData.read(io.BytesIO(ply.content))["vertex"]
        assert vertices.count > 0


def test_a_frame_is_rendered_as_its_photo_shows_it_under_auto_exposure(engine_stack):
    """The camera darkens to 0.6 of its gain halfway (auto-exposure): the map keeps normalised colours, and a render
    with `exposure_of` a late frame's seq shows them as that frame's photo does (darker); a bad seq is refused."""
    frames = icl_frames(FRAMES, scale=SCALE)
    gain = 0.6
    for frame in frames[FRAMES // 2:]:
        bgr = decode_png(frame["jpeg"], cv2.IMREAD_COLOR)
        darker = (bgr * gain).round().astype(np.uint8)
        frame["jpeg"] = cv2.imencode(".jpg", darker, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    with httpx.Client(base_url=engine_stack.base_url, timeout=180) as api:
        sid = api.post("/v1/sessions", json={"intrinsics": INTRINSICS, "preset": "test", "name": "exposure"}
                       ).json()["id"]
        with connect(f"{engine_stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            for seq, frame in enumerate(frames):
                ws.send(frame_message(seq, frame, with_pose=True, with_depth=True))
            ws.send(json.dumps({"type": "finish"}))
            messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=240)
            assert not of_type(messages, "error"), of_type(messages, "error")
        last = ",".join(f"{v:.9g}" for v in frames[-1]["pose"])

        def mean_brightness(**params) -> float:
            reply = api.get(f"/v1/sessions/{sid}/render", params={"pose": last, **params})
            assert reply.status_code == 200, reply.text
            return float(decode_png(reply.content, cv2.IMREAD_COLOR).mean())

        normalised, early = mean_brightness(), mean_brightness(exposure_of=0)
        late = mean_brightness(exposure_of=FRAMES - 1)
        photo = float(decode_png(frames[-1]["jpeg"], cv2.IMREAD_COLOR).mean())
        assert abs(early - normalised) < 1.0  # the first keyframe fixes the map's colour scale
        assert late < 0.8 * normalised and abs(late - photo) < 0.1 * photo, (normalised, late, photo)
        assert api.get(f"/v1/sessions/{sid}/render", params={"pose": last, "exposure_of": -1}).status_code == 422
