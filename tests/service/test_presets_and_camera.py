"""Clients can discover the presets (GET /v1/presets), ask for device poses to be kept (`pose_mode`), and read the
camera the engine works with (`estimated_intrinsics` on the session and the trajectory)."""

from __future__ import annotations

import math

import httpx
import pytest
from conftest import STREAM_KEY
from service_helpers import frame_message, icl_frames, receive_until
from websockets.sync.client import connect

from client.streaming import open_frames
from protocol.presets import ENGINE_PRESETS, PresetName
from service.presets import PRESET_INFO
from worker.config import PRESETS
from worker.runtime.engine import close_engine, create_engine, engine_intrinsics

FRAMES = icl_frames(3)
FRAME_K = {"fx": 250.0, "fy": 251.0, "cx": 160.5, "cy": 119.5}


def test_the_documented_presets_are_the_engine_s():
    # `auto` is the worker's choice among the engine's presets, not one of its own
    assert set(PRESET_INFO) == set(PresetName.__args__) == set(PRESETS) | {"auto"}
    assert set(ENGINE_PRESETS) == set(PRESETS)


def test_presets_are_listed_for_any_valid_key(api, stack):
    body = api.get("/v1/presets").json()
    assert [p["name"] for p in body["presets"]] == list(PRESET_INFO)
    assert all(p["purpose"] and p["input"] for p in body["presets"])
    assert "depth" in body["input_modes"] and "pose" in body["input_modes"]
    assert httpx.get(f"{stack.base_url}/v1/presets").status_code == 401


def test_pose_mode_is_recorded_and_validated(api):
    created = api.post("/v1/sessions", json={"pose_mode": "fixed", "preset": "rgbd"}).json()
    assert created["pose_mode"] == "fixed"
    assert api.get(f"/v1/sessions/{created['id']}").json()["pose_mode"] == "fixed"
    refused = api.post("/v1/sessions", json={"pose_mode": "frozen"})
    assert refused.status_code == 422 and refused.json()["detail"][0]["loc"] == ["body", "pose_mode"]


@pytest.mark.parametrize("pose_mode, expected", [("fixed", "fixed"), ("seeded", "seeded"), (None, "auto")])
def test_pose_mode_reaches_the_engine(pose_mode, expected):
    engine = create_engine("slam", "test", None, pose_mode=pose_mode)
    try:
        assert engine.config.input.pose_mode == expected and engine.config.name == "test"
    finally:
        close_engine(engine)


def test_the_engine_s_camera_is_returned_with_the_session_and_trajectory(api, stack):
    sid = api.post("/v1/sessions", json={}).json()["id"]
    assert api.get(f"/v1/sessions/{sid}").json()["estimated_intrinsics"] is None
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", additional_headers={"X-API-Key": STREAM_KEY},
                 open_timeout=20) as ws:
        for seq, frame in enumerate(FRAMES):
            ws.send(frame_message(seq, frame, intrinsics=FRAME_K))
        ws.send('{"type": "finish"}')
        receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
    camera = {**FRAME_K, "width": 320, "height": 240}
    assert api.get(f"/v1/sessions/{sid}").json()["estimated_intrinsics"] == pytest.approx(camera)
    assert api.get(f"/v1/sessions/{sid}/trajectory").json()["intrinsics"] == pytest.approx(camera)


def test_given_intrinsics_are_the_camera_before_any_frame(api):
    given = {"fx": 262.5, "fy": 262.5, "cx": 159.75, "cy": 119.75, "width": 320, "height": 240}
    created = api.post("/v1/sessions", json={"intrinsics": given}).json()
    assert created["estimated_intrinsics"] == given


def test_the_slam_engine_reports_the_camera_it_uses_for_monocular_frames(data_dir):
    engine = create_engine("slam", "test", None)
    try:
        assert engine_intrinsics(engine) is None  # nothing known before a frame
        for frame in open_frames(data_dir / "icl_mini", max_frames=2):
            frame.intrinsics, frame.depth, frame.pose = None, None, None  # a phone without intrinsics
            engine.push(frame)
        camera = engine_intrinsics(engine)
    finally:
        close_engine(engine)
    assert (camera["width"], camera["height"]) == (320, 240)
    assert all(math.isfinite(camera[k]) and camera[k] > 0 for k in ("fx", "fy", "cx", "cy"))
