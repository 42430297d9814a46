"""Fairness and lifecycle: idle sessions are abandoned (freeing their worker slot) and resumable within a grace
period, and each API key has a quota of live sessions."""

from __future__ import annotations

import json
import time

import httpx
import pytest
import redis
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack

KEYS = "key-a=stream,read;key-b=stream,read;key-c=stream,read"
GRACE_S = 6.0


@pytest.fixture(scope="module")
def stack():
    worker_env = {**WORKER_ENV, "FLASHMONO_IDLE_TIMEOUT_S": "2", "FLASHMONO_MAX_SESSIONS": "2"}
    gateway_env = {"FLASHMONO_API_KEYS": KEYS, "FLASHMONO_MAX_LIVE_SESSIONS": "3",
                   "FLASHMONO_ABANDONED_GRACE_S": str(GRACE_S)}
    with LocalStack(workers=1, worker_env=worker_env, gateway_env=gateway_env) as local:
        yield local


def client(stack, key: str) -> httpx.Client:
    return httpx.Client(base_url=stack.base_url, headers={"X-API-Key": key}, timeout=30)


def stream(stack, sid: str, key: str):
    return connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", additional_headers={"X-API-Key": key},
                   open_timeout=20)


def finished_session(local: LocalStack, api: httpx.Client, frames: int) -> str:
    """A new session that streamed `frames` frames and finished."""
    sid = api.post("/v1/sessions", json={}).json()["id"]
    with connect(f"{local.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
        for seq in range(frames):
            ws.send(synthetic_frame(seq))
        ws.send(json.dumps({"type": "finish"}))
        receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
    return sid


def status(api: httpx.Client, sid: str) -> str:
    return api.get(f"/v1/sessions/{sid}").json()["status"]


def test_idle_sessions_free_their_slot_and_resume_within_the_grace_period(stack):
    with client(stack, "key-a") as api:
        # two sessions that streamed a frame and went silent hold the worker's two slots until abandoned (2 s idle)
        idle = [api.post("/v1/sessions", json={"name": "idle"}).json()["id"] for _ in range(2)]
        for sid in idle:
            with stream(stack, sid, "key-a") as ws:
                ws.send(synthetic_frame(0))
                receive_until(ws, lambda m: m["type"] == "pose", timeout_s=60)
        sid = api.post("/v1/sessions", json={"name": "walk"}).json()["id"]
        t0 = time.monotonic()
        with stream(stack, sid, "key-a") as ws:
            for seq in range(3):
                ws.send(synthetic_frame(seq))
            receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == 2, timeout_s=60)
            waited = time.monotonic() - t0
            assert "abandoned" in {status(api, s) for s in idle}  # an idle one made room for it
            assert waited < 30
            # now this one goes idle too, and is told so
            abandoned = receive_until(ws, lambda m: m.get("code") == "abandoned", timeout_s=30)[-1]
            assert "grace period" in abandoned["message"]
        assert status(api, sid) == "abandoned"
        with stream(stack, sid, "key-a") as ws:  # within the grace period: it resumes where it stopped
            for seq in range(3, 6):
                ws.send(synthetic_frame(seq))
            ws.send(json.dumps({"type": "finish"}))
            messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
        assert [m["seq"] for m in messages if m["type"] == "pose"] == [3, 4, 5]
        poses = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
        assert [p["seq"] for p in poses] == list(range(6)) and all(p["pose"][3] == p["seq"] for p in poses)
        # past the grace period an abandoned session stays closed, with the reason
        wait_for(lambda: time.monotonic() - t0 > GRACE_S + 3, timeout_s=30, interval_s=0.2)  # idle ~2 s, then grace
        with stream(stack, idle[0], "key-a") as ws:
            refusal = json.loads(ws.recv(timeout=10))
        assert refusal["code"] == "not_accepting" and "can no longer be resumed" in refusal["message"]


def test_sessions_nobody_streams_to_hold_no_worker_slot(stack):
    with client(stack, "key-c") as api:
        flood = [api.post("/v1/sessions", json={"name": "flood"}).json()["id"] for _ in range(3)]  # the key's quota
        wait_for(lambda: all(status(api, s) == "abandoned" for s in flood), timeout_s=30)  # no frame within 2 s
        flood = [api.post("/v1/sessions", json={"name": "flood"}).json()["id"] for _ in range(2)]
        sid = api.post("/v1/sessions", json={"name": "real"}).json()["id"]
        t0 = time.monotonic()
        with stream(stack, sid, "key-c") as ws:  # both slots are free: the flood took none
            ws.send(synthetic_frame(0))
            receive_until(ws, lambda m: m["type"] == "pose", timeout_s=60)
        assert time.monotonic() - t0 < 1.9  # before any idle session could have been abandoned to make room
        assert {status(api, s) for s in flood} <= {"created", "abandoned"}


def test_each_key_has_a_quota_of_live_sessions(stack):
    with client(stack, "key-b") as b, client(stack, "key-a") as a:
        live = [b.post("/v1/sessions", json={}).json()["id"] for _ in range(3)]
        refused = b.post("/v1/sessions", json={})
        assert refused.status_code == 429 and "3 live sessions" in refused.json()["detail"]
        assert a.post("/v1/sessions", json={}).status_code == 201  # another key's quota is its own
        assert b.delete(f"/v1/sessions/{live[0]}").status_code == 204
        assert b.post("/v1/sessions", json={}).status_code == 201  # a deleted one no longer counts
        wait_for(lambda: status(b, live[1]) == "abandoned", timeout_s=30)  # nor do abandoned ones
        assert b.post("/v1/sessions", json={}).status_code == 201


def test_ended_sessions_expire_live_data_then_everything_after_the_retention():
    worker_env = {**WORKER_ENV, "FLASHMONO_TRANSIENT_TTL_S": "2", "FLASHMONO_RETENTION_S": "6"}
    with LocalStack(workers=1, worker_env=worker_env) as local, \
            httpx.Client(base_url=local.base_url, timeout=30) as api:
        r = redis.Redis.from_url(local.redis_url)
        sid = finished_session(local, api, frames=4)
        live_only = [keys.inbox(sid), keys.outbox(sid)]
        assert all(0 < r.pttl(k) <= 2000 for k in live_only)
        wait_for(lambda: not any(r.exists(k) for k in live_only), timeout_s=10)
        # the results stay until the retention ends
        assert len(api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]) == 4
        assert api.get(f"/v1/sessions/{sid}/map.ply").status_code == 200
        wait_for(lambda: api.get(f"/v1/sessions/{sid}").status_code == 404, timeout_s=15, interval_s=0.2)
        assert [k for k in r.scan_iter(match=f"*{sid}*") if k != keys.lease(sid).encode()] == []
        assert api.get("/v1/sessions").json()["sessions"] == []  # the listing skips what expired


def test_finished_sessions_move_to_the_blob_store_and_stay_downloadable(tmp_path):
    blobs = {"FLASHMONO_BLOB_DIR": str(tmp_path / "blobs")}
    worker_env = {**WORKER_ENV, **blobs, "FLASHMONO_ARCHIVE_AFTER_S": "1"}
    with LocalStack(workers=1, worker_env=worker_env, gateway_env=blobs) as local, \
            httpx.Client(base_url=local.base_url, timeout=30) as api:
        r = redis.Redis.from_url(local.redis_url)
        sid = finished_session(local, api, frames=4)
        before = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
        ply = api.get(f"/v1/sessions/{sid}/map.ply").content
        wait_for(lambda: r.hget(keys.session(sid), "archived") == b"1", timeout_s=30)
        assert not r.exists(keys.snapshot(sid)) and not r.exists(keys.poses(sid))
        assert (tmp_path / "blobs" / sid / "snapshot.msgpack").is_file()
        assert api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"] == before
        assert api.get(f"/v1/sessions/{sid}/map.ply").content == ply
        assert api.get(f"/v1/sessions/{sid}").json()["status"] == "finished"
        assert api.delete(f"/v1/sessions/{sid}").status_code == 204
        assert not (tmp_path / "blobs" / sid).exists()
