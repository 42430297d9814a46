"""Backpressure keeps the order: after frame N is refused for a full queue, every later seq is refused with
`resend_from: N` (even once the queue has room) until N is re-sent, so a pipelining sender can always re-send N."""

from __future__ import annotations

import cv2
import httpx
import msgpack
import numpy as np
import pytest
from service_helpers import receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

MAX_QUEUE = 2
WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LOG_LEVEL": "WARNING"}
JPEG = cv2.imencode(".jpg", np.full((48, 64, 3), 90, np.uint8))[1].tobytes()


def synthetic_message(seq: int) -> bytes:
    return msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30.0, "image": JPEG})


@pytest.fixture(scope="module")
def stack():
    """No worker at first, so the queue fills deterministically; the test adds one to drain it."""
    with LocalStack(workers=0, worker_env=WORKER_ENV,
                    gateway_env={"FLASHMONO_MAX_QUEUE": str(MAX_QUEUE)}) as local:
        yield local


def _answer(ws, seq: int) -> dict:
    ws.send(synthetic_message(seq))
    return receive_until(ws, lambda m: m["type"] in ("ack", "error"))[-1]


def test_frames_after_a_refused_one_wait_for_its_resend(stack):
    with httpx.Client(base_url=stack.base_url, timeout=30) as api:
        sid = api.post("/v1/sessions", json={"name": "order"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            assert [_answer(ws, s)["type"] for s in (0, 1)] == ["ack", "ack"]
            refused = _answer(ws, 2)
            assert (refused["code"], refused["seq"], refused["resend_from"], refused["queue_depth"]) == (
                "backpressure", 2, 2, MAX_QUEUE)
            held = _answer(ws, 3)
            assert (held["code"], held["resend_from"]) == ("backpressure", 2)
            assert "resend from seq 2" in held["message"]

            stack.add_worker()
            stack.wait_ready(180, need_workers=1)
            receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == 1, timeout_s=120)
            still_held = _answer(ws, 5)  # the queue is empty now, but 2 has not been re-sent
            assert (still_held["code"], still_held["resend_from"]) == ("backpressure", 2)
            assert [_answer(ws, s)["type"] for s in (2, 3)] == ["ack", "ack"]
            # 2 and 3 fill the queue again: 5 is taken once the worker has drained them
            receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == 3, timeout_s=120)
            assert _answer(ws, 5)["type"] == "ack"
            assert _answer(ws, 4)["code"] == "bad_seq"  # a gap the sender left stays a gap
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["frames_received"] == 5
