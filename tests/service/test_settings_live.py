"""A session created as openapi.yaml shows it (no preset) gets its settings from the worker at its first frame,
from what it receives and the worker's machine; the session record and GET /v1/presets say what was chosen and
why; a named preset is kept. Real gateway, worker (the real engine) and Redis."""

from __future__ import annotations

import json
import os

import httpx
import pytest
from service_helpers import frame_message, icl_frames, of_type, receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

VGA = {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}


@pytest.fixture(scope="module")
def engine_stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_LEASE_TTL_MS": "10000", "FLASHMONO_TORCH_THREADS": "2",
           "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=env, gateway_env={"FLASHMONO_REQUEST_TIMEOUT_S": "120"}) as stack:
        yield stack


@pytest.fixture(scope="module")
def vga_frames() -> list[dict]:
    return icl_frames(4, scale=2.0)  # a 640x480 camera


def stream(stack, api: httpx.Client, body: dict, frames: list[dict], with_depth: bool) -> tuple[dict, list[dict]]:
    """Create a session with `body`, stream `frames`, finish; (the session record, every message)."""
    created = api.post("/v1/sessions", json=body)
    assert created.status_code == 201, created.text
    session = created.json()
    if "preset" not in body:  # nothing decided before the first frame
        assert session["settings"] is None and session["preset"] is None
    with connect(f"{stack.ws_url}/v1/sessions/{session['id']}/stream", open_timeout=30) as ws:
        for seq, frame in enumerate(frames):
            ws.send(frame_message(seq, frame, with_depth=with_depth))
        ws.send(json.dumps({"type": "finish"}))
        messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=240)
    assert not of_type(messages, "error"), of_type(messages, "error")
    return api.get(f"/v1/sessions/{session['id']}").json(), messages


def test_a_live_rgbd_session_without_a_preset_is_decided_at_its_first_frame(engine_stack, vga_frames):
    with httpx.Client(base_url=engine_stack.base_url, timeout=120) as api:
        body = {"name": "phone", "intrinsics": VGA, "skip_frames": True, "frame_rate": 30}
        session, messages = stream(engine_stack, api, body, vga_frames, with_depth=True)
    settings = session["settings"]
    assert session["status"] == "finished" and session["frame_rate"] == 30
    assert settings["decided"] == "auto" and settings["preset"] == session["preset"] == "rgbd"
    # a live stream over 320 px on a CPU: tracked and mapped at 320 px, the camera scaled with it
    assert settings["working_side"] == 320 and settings["tracking_side"] is None
    assert session["estimated_intrinsics"]["width"] == 320 and session["estimated_intrinsics"]["fx"] == 262.5
    assert settings["reasons"][-1].startswith("input: rgbd;")
    assert any("30 frames/s" in reason for reason in settings["reasons"])
    finishing = of_type(messages, "finishing")
    assert finishing and all("phase" in m for m in finishing[1:])  # the finish says where it is
    # every frame posed, or skipped by a tracker behind a stream sent at once (each says so)
    assert len(of_type(messages, "pose")) + len(of_type(messages, "skipped")) == len(vga_frames)
    assert of_type(messages, "pose")[0]["seq"] == 0


def test_recorded_frames_keep_their_size_and_a_named_preset_is_kept(engine_stack, vga_frames):
    with httpx.Client(base_url=engine_stack.base_url, timeout=120) as api:
        rgb, _ = stream(engine_stack, api, {"intrinsics": VGA}, vga_frames[:3], with_depth=False)
        named, _ = stream(engine_stack, api, {"intrinsics": VGA, "preset": "test", "skip_frames": True},
                          vga_frames[:3], with_depth=True)
    assert rgb["settings"]["decided"] == "auto" and rgb["settings"]["working_side"] is None
    assert rgb["settings"]["reasons"][-1].startswith("input: rgb;")
    assert rgb["estimated_intrinsics"]["width"] == 640
    assert named["settings"]["decided"] == "named" and named["preset"] == named["settings"]["preset"] == "test"


def test_the_presets_say_what_auto_chooses_on_the_workers_machines(engine_stack):
    with httpx.Client(base_url=engine_stack.base_url, timeout=30) as api:
        body = api.get("/v1/presets").json()
        refused = api.post("/v1/sessions", json={"preset": "quick"})
    assert body["presets"][0]["name"] == "auto"
    [kind] = body["auto_choices"]
    assert kind["workers"] == 1 and kind["machine"]["cpu_cores"] == len(os.sched_getaffinity(0))
    assert kind["machine"]["cuda"] is False and kind["machine"]["trained_weights"] is False
    assert set(kind["live"]) == {"rgbd", "posed-rgbd", "posed-rgb", "rgb"}
    assert kind["live"]["rgbd"]["working_side"] == 320 and kind["recorded"]["rgbd"]["working_side"] is None
    assert all(choice["preset"] == "rgbd" for choice in kind["live"].values())
    assert refused.status_code == 422
