"""Live tracking through the real stack: when the worker falls behind a stream, frames that waited too long while a
newer one waits get a `skipped` message (newest first wins, a few in a row at most), never silence; a session that
asks for every frame gets a pose for each, however late."""

from __future__ import annotations

import time

import cv2
import httpx
import msgpack
import numpy as np
import pytest
from service_helpers import receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

FRAMES = 16
# The passthrough engine takes 120 ms a frame, the skip limit is 50 ms: a burst of frames falls behind at once.
WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LOG_LEVEL": "WARNING",
              "FLASHMONO_PASSTHROUGH_DELAY_MS": "120", "FLASHMONO_SKIP_AFTER_MS": "50",
              "FLASHMONO_MAX_CONSECUTIVE_SKIPS": "3"}
JPEG = cv2.imencode(".jpg", np.full((48, 64, 3), 90, np.uint8))[1].tobytes()


@pytest.fixture(scope="module")
def stack():
    with LocalStack(workers=1, worker_env=WORKER_ENV) as local:
        yield local


def _stream_burst(stack: LocalStack, body: dict, every_s: float = 0.0) -> tuple[str, dict[int, str]]:
    """Send FRAMES frames at once (or one every `every_s`); returns the session id and each seq's result type (pose
    or skipped)."""
    with httpx.Client(base_url=stack.base_url, timeout=30) as api:
        sid = api.post("/v1/sessions", json=body).json()["id"]
    results: dict[int, str] = {}
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
        for seq in range(FRAMES):
            ws.send(msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30.0, "image": JPEG}))
            time.sleep(every_s)

        def record(message: dict) -> bool:
            if message["type"] in ("pose", "skipped"):
                assert message["seq"] not in results, "a seq got two results"
                results[message["seq"]] = message["type"]
            assert message["type"] != "error", message
            return len(results) == FRAMES

        receive_until(ws, record, timeout_s=120)
    return sid, results


def test_a_stream_the_worker_cannot_keep_up_with_skips_old_frames_with_a_message(stack):
    sid, results = _stream_burst(stack, {"name": "live", "skip_frames": True})
    skipped = sorted(s for s, kind in results.items() if kind == "skipped")
    assert skipped, "the worker fell behind, yet no frame was skipped"
    assert results[0] == "pose" and results[FRAMES - 1] == "pose"  # the first frame and the newest are tracked
    assert _longest_skipped_run(results) <= 3
    with httpx.Client(base_url=stack.base_url, timeout=30) as api:
        session = api.get(f"/v1/sessions/{sid}").json()
    assert session["frames_skipped"] == len(skipped)
    assert session["frames_processed"] == FRAMES - len(skipped)
    assert session["skip_frames"] is True and session["tracking_state"] == "tracking"


def _longest_skipped_run(results: dict[int, str]) -> int:
    run = longest = 0
    for seq in range(FRAMES):
        run = run + 1 if results[seq] == "skipped" else 0
        longest = max(longest, run)
    return longest


def test_frames_skipped_in_a_row_span_no_more_time_than_the_limit():
    """A stream of frames 50 ms apart (a 20 frames/s camera) that the worker falls behind: frames are skipped, but
    never two in a row, as the second would have arrived 100 ms after the last tracked frame, over the 80 ms the
    worker allows (`FLASHMONO_MAX_SKIPPED_SPAN_MS`): the motion across a gap grows with its time."""
    env = {**WORKER_ENV, "FLASHMONO_MAX_CONSECUTIVE_SKIPS": "5", "FLASHMONO_MAX_SKIPPED_SPAN_MS": "80"}
    with LocalStack(workers=1, worker_env=env) as local:
        _, results = _stream_burst(local, {"name": "live", "skip_frames": True}, every_s=0.05)
    assert "skipped" in results.values(), "the worker fell behind, yet no frame was skipped"
    assert _longest_skipped_run(results) == 1


def test_a_session_by_default_gets_a_pose_for_every_frame(stack):
    sid, results = _stream_burst(stack, {"name": "recorded"})
    assert set(results.values()) == {"pose"}
    with httpx.Client(base_url=stack.base_url, timeout=30) as api:
        session = api.get(f"/v1/sessions/{sid}").json()
    assert session["frames_skipped"] == 0 and session["skip_frames"] is False


def test_a_session_names_its_tracking_resolution_and_a_bad_one_is_refused(stack):
    with httpx.Client(base_url=stack.base_url, timeout=30) as api:
        created = api.post("/v1/sessions", json={"name": "vga", "tracking_side": 320})
        assert created.status_code == 201, created.text
        assert api.get(f"/v1/sessions/{created.json()['id']}").json()["tracking_side"] == 320
        assert api.post("/v1/sessions", json={"name": "plain"}).json()["tracking_side"] is None
        refused = api.post("/v1/sessions", json={"name": "tiny", "tracking_side": 8})
        assert refused.status_code == 422 and "tracking_side" in refused.text


def test_the_engine_of_a_session_tracks_at_its_tracking_resolution():
    from worker.runtime.engine import create_engine

    engine = create_engine("slam", "test", None, tracking_side=320)
    assert engine.config.tracking.max_side == 320
    assert create_engine("slam", "test", None).config.tracking.max_side == 0
