"""A real redis-server killed (SIGKILL) mid-stream and started again on its append-only file: the gateway and the
worker ride the outage out (no process exits), frames sent meanwhile are acknowledged after it or refused with
`unavailable` and re-sent, and every acknowledged frame ends up in the trajectory exactly once."""

from __future__ import annotations

import collections
import json
import threading
import time

import httpx
import pytest
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from service.launcher import LocalStack
from service.redis_embedded import EmbeddedRedis

FRAMES = 60
KILL_AT = 20
OUTAGE_S = 6.0  # the chaos benchmark measures 60 s; the suite keeps it short


@pytest.fixture
def redis_server(tmp_path):
    server = EmbeddedRedis(data_dir=tmp_path / "redis").start()
    yield server
    server.stop()


def stream_through_outage(ws, redis_server: EmbeddedRedis) -> tuple[set[int], list[dict], int]:
    """Send FRAMES frames one at a time, re-sending refused ones; kill Redis after KILL_AT acks and start it again
    OUTAGE_S later. (acked seqs, every message received, refusals)."""
    acked: set[int] = set()
    messages: list[dict] = []
    refusals = 0
    seq = 0
    restart: threading.Timer | None = None
    while seq < FRAMES:
        if seq == KILL_AT and restart is None:
            redis_server.kill()
            restart = threading.Timer(OUTAGE_S, redis_server.start)
            restart.start()
        ws.send(synthetic_frame(seq))
        got = receive_until(ws, lambda m, s=seq: m["type"] in ("ack", "error") and m.get("seq") == s, timeout_s=60)
        messages += got
        answer = got[-1]
        if answer["type"] == "ack":
            acked.add(seq)
            seq += 1
            continue
        assert answer["code"] == "unavailable" and "resend" in answer["message"], answer
        refusals += 1
        seq = answer["resend_from"]
        time.sleep(0.2)
    restart.join()
    return acked, messages, refusals


def test_redis_killed_and_restarted_mid_stream_loses_no_acked_frame(redis_server):
    env = {**WORKER_ENV, "FLASHMONO_PASSTHROUGH_DELAY_MS": "20"}
    with LocalStack(workers=1, redis_url=redis_server.url, worker_env=env) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=30) as api:
        sid = api.post("/v1/sessions", json={"name": "outage"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            acked, messages, refusals = stream_through_outage(ws, redis_server)
            ws.send(json.dumps({"type": "finish"}))
            messages += receive_until(ws, lambda m: m["type"] == "finished", timeout_s=120)
        assert acked == set(range(FRAMES))
        assert refusals >= 1  # the outage was seen by the client, as a clear refusal it could act on
        # no process exited: the same gateway and worker serve on
        assert stack.gateway.poll() is None and all(w.poll() is None for w in stack.workers)
        poses = collections.Counter(m["seq"] for m in messages if m["type"] == "pose")
        assert set(poses) == acked and set(poses.values()) == {1}
        trajectory = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
        assert [p["seq"] for p in trajectory] == sorted(acked)
        assert all(p["pose"][3] == p["seq"] for p in trajectory)
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["status"] == "finished"
        assert session["frames_received"] == session["frames_processed"] == FRAMES
        wait_for(lambda: api.get("/readyz").status_code == 200, timeout_s=30)


def test_http_answers_json_503_while_redis_is_down(redis_server):
    with LocalStack(workers=0, redis_url=redis_server.url) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={}).json()["id"]
        redis_server.kill()
        try:
            r = api.get(f"/v1/sessions/{sid}")
            assert r.status_code == 503 and "unreachable" in r.json()["detail"]
            assert api.get("/readyz").json() == {"status": "not_ready", "redis": False, "workers": 0}
            with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
                assert json.loads(ws.recv(timeout=60))["code"] == "unavailable"
        finally:
            redis_server.start()
        assert api.get(f"/v1/sessions/{sid}").json()["id"] == sid  # persisted and served again
        assert stack.gateway.poll() is None
