"""A session's first frame starts it at once: the gateway queues a job with it, so a worker does not wait for its
next look at the sessions created without frames (their first job is deferred); the deferred job is acked, on the
worker that ran the session or on another one, and nothing stays pending."""

from __future__ import annotations

import json
import time

import httpx
import redis
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack


def _jobs_of(client: redis.Redis, session_id: str) -> list[bytes]:
    stream = keys.jobs(session_id)
    return [entry_id for entry_id, fields in client.xrange(stream) if fields[b"session_id"] == session_id.encode()]


def _pending_jobs(client: redis.Redis, session_id: str) -> list[bytes]:
    ours = set(_jobs_of(client, session_id))
    pending = client.xpending_range(keys.jobs(session_id), keys.GROUP, min="-", max="+", count=1000)
    return [entry["message_id"] for entry in pending if entry["message_id"] in ours]


def test_the_first_frame_wakes_a_worker_and_the_deferred_job_is_acked() -> None:
    with LocalStack(workers=2, worker_env=WORKER_ENV) as stack:
        client = redis.Redis.from_url(stack.redis_url)
        with httpx.Client(base_url=stack.base_url, timeout=30) as api:
            for _ in range(2):  # either worker may hold the deferred job and either may read the new one
                sid = api.post("/v1/sessions", json={"name": "first-frame"}).json()["id"]
                wait_for(lambda sid=sid: _pending_jobs(client, sid), timeout_s=10)  # a worker read and deferred it
                time.sleep(0.6)  # past a deferred check: the session still has no frame
                assert len(_jobs_of(client, sid)) == 1
                with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
                    for seq in range(3):
                        ws.send(synthetic_frame(seq))
                    receive_until(ws, lambda m: m["type"] == "pose", timeout_s=30)
                    assert len(_jobs_of(client, sid)) == 2, "the first frame queues the session's job again"
                    # while it streams, only the running job is pending: the deferred one is acked wherever it was
                    wait_for(lambda sid=sid: len(_pending_jobs(client, sid)) == 1, timeout_s=10)
                    ws.send(json.dumps({"type": "finish"}))
                    receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
                wait_for(lambda sid=sid: not _pending_jobs(client, sid), timeout_s=10)
                record = api.get(f"/v1/sessions/{sid}").json()
                assert record["status"] == "finished" and record["frames_processed"] == 3
        client.close()
