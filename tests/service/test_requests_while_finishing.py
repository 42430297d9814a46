"""While a session finishes (the engine's final refinement: tens of seconds), its map and renders are answered at
once, not after the finish: a real gateway, worker and redis-server, the passthrough engine with a slow finish."""

from __future__ import annotations

import json
import time

import httpx
import pytest
from service_helpers import ICL_INTRINSICS, frame_message, icl_frames, receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

FINISH_MS = 8000
FRAME_MS = 1000
FRAMES = 4
INTRINSICS = {k: (v * 0.5 if k in ("fx", "fy", "cx", "cy") else int(v * 0.5)) for k, v in ICL_INTRINSICS.items()}


@pytest.fixture(scope="module")
def slow_finish_stack():
    worker_env = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_PASSTHROUGH_FINISH_MS": str(FINISH_MS),
                  "FLASHMONO_PASSTHROUGH_DELAY_MS": str(FRAME_MS), "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=worker_env) as stack:
        yield stack


def test_map_and_render_requests_are_answered_while_the_session_finishes(slow_finish_stack):
    stack = slow_finish_stack
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"name": "slow finish", "intrinsics": INTRINSICS}).json()["id"]
        frames = icl_frames(FRAMES, scale=0.5)
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            for seq, frame in enumerate(frames):
                ws.send(frame_message(seq, frame, with_pose=True))
            receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == FRAMES - 1, timeout_s=60)
            ws.send(json.dumps({"type": "finish"}))
            receive_until(ws, lambda m: m["type"] == "finishing", timeout_s=60)
            began = time.monotonic()
            ply = api.get(f"/v1/sessions/{sid}/map", params={"format": "ply"})
            pose = ",".join(f"{v:.9g}" for v in frames[0]["pose"])
            render = api.get(f"/v1/sessions/{sid}/render", params={"pose": pose})
            answered_after = time.monotonic() - began
            status = api.get(f"/v1/sessions/{sid}").json()["status"]
            finished = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
        assert ply.status_code == 200 and ply.content.startswith(b"ply"), ply.text[:200]
        assert render.status_code == 200 and render.headers["content-type"] == "image/png", render.text[:200]
        # answered before the finish ended (the old runner answered both after it, the session then "finished")
        assert status == "finishing", (status, answered_after)
        assert finished[-1] == {"type": "finished", "frames": FRAMES}
        assert api.get(f"/v1/sessions/{sid}").json()["status"] == "finished"


def test_a_request_read_together_with_the_finish_is_answered_before_the_finish(slow_finish_stack):
    """The frames queue up (a second each) in a running session, the finish and a map request behind them: the
    worker reads the last frames, the finish and the request in one go, and answers the request before it starts
    finishing."""
    stack = slow_finish_stack
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"name": "queued finish", "intrinsics": INTRINSICS}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            frames = icl_frames(FRAMES, scale=0.5)
            ws.send(frame_message(0, frames[0], with_pose=True))
            receive_until(ws, lambda m: m["type"] == "pose", timeout_s=60)  # the worker's session runs
            for seq, frame in enumerate(frames[1:], start=1):
                ws.send(frame_message(seq, frame, with_pose=True))
            time.sleep(0.5)  # the worker reads the next frames and works on them ...
            ws.send(json.dumps({"type": "finish"}))  # ... while the finish and the request queue up behind
            ply = api.get(f"/v1/sessions/{sid}/map", params={"format": "ply"})
            status = api.get(f"/v1/sessions/{sid}").json()["status"]
            receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
        assert ply.status_code == 200 and ply.content.startswith(b"ply"), ply.text[:200]
        assert status == "finishing"
