"""A gateway stopped (SIGSTOP) for 10 s mid-stream: afterwards every open stream gets its acks and its poses again
(the per-stream forwarding survives the stall: a timed-out Redis read is retried from the last entry sent)."""

from __future__ import annotations

import contextlib
import json
import signal
import time

import httpx
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame
from websockets.sync.client import connect

from service.launcher import LocalStack

STREAMS = 3
BEFORE, AFTER = 5, 5
STALL_S = 10.0


def test_streams_deliver_poses_after_a_10s_gateway_stall():
    with LocalStack(workers=1, worker_env=WORKER_ENV) as stack, httpx.Client(base_url=stack.base_url) as api:
        sids = [api.post("/v1/sessions", json={"name": f"stall-{i}"}).json()["id"] for i in range(STREAMS)]
        with contextlib.ExitStack() as opened:
            sockets = [opened.enter_context(connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20))
                       for sid in sids]
            for ws in sockets:
                for seq in range(BEFORE):
                    ws.send(synthetic_frame(seq))
                receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == BEFORE - 1, timeout_s=60)
            stack.gateway.send_signal(signal.SIGSTOP)
            time.sleep(STALL_S)  # the worker keeps publishing results meanwhile; nothing is read
            stack.gateway.send_signal(signal.SIGCONT)
            for ws in sockets:
                for seq in range(BEFORE, BEFORE + AFTER):
                    ws.send(synthetic_frame(seq))
                ws.send(json.dumps({"type": "finish"}))
            for ws in sockets:
                messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
                poses = [m["seq"] for m in messages if m["type"] == "pose"]
                acks = [m["seq"] for m in messages if m["type"] == "ack"]
                assert acks == list(range(BEFORE, BEFORE + AFTER))
                assert poses == list(range(BEFORE, BEFORE + AFTER))
        assert stack.gateway.poll() is None
