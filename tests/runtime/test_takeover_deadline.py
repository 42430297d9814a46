"""A standby worker wakes when a silent worker's job goes stale (its last heartbeat plus a lease), not at its next
poll: the deadline it computes from the pending jobs' idle times is the moment the job can be claimed. Real Redis."""

from __future__ import annotations

import time

import pytest
import redis

from protocol import keys
from service.redis_embedded import EmbeddedRedis
from worker.runtime.consumer import Worker
from worker.runtime.sessions import RuntimeConfig

TTL_MS = 2000


@pytest.fixture()
def client():
    with EmbeddedRedis() as server:
        yield redis.Redis.from_url(server.url)


def _pending_for(client: redis.Redis, stream: str, consumer: str) -> int:
    return sum(1 for entry in client.xpending_range(stream, keys.GROUP, min="-", max="+", count=10)
               if entry["consumer"] == consumer.encode())


def test_standby_claims_a_silent_workers_job_at_the_deadline_it_computed(client) -> None:
    standby = Worker(client, "standby", RuntimeConfig(lease_ttl_ms=TTL_MS))
    standby._ensure_groups()
    stream = keys.jobs("sessionx")
    client.xadd(stream, {"session_id": "sessionx"})
    client.xreadgroup(keys.GROUP, "dead", {stream: ">"}, count=1)  # the job of a worker that then goes silent
    time.sleep(0.55 * TTL_MS / 1000)  # past half a lease: the deadline comes from the job's idle time
    deadline = standby._next_stale_at()
    assert deadline - time.monotonic() < TTL_MS / 2000  # sooner than the half-lease fallback
    standby._claim_stale_jobs()
    assert _pending_for(client, stream, "dead") == 1  # not stale yet: nothing to take
    time.sleep(max(0.0, deadline - time.monotonic()))
    standby._claim_stale_jobs()  # the session's record is gone here, so the claimed job is acknowledged
    assert _pending_for(client, stream, "dead") == 0
    assert client.xpending(stream, keys.GROUP)["pending"] == 0


def test_deadline_ignores_the_workers_own_jobs(client) -> None:
    worker = Worker(client, "me", RuntimeConfig(lease_ttl_ms=TTL_MS))
    worker._ensure_groups()
    stream = keys.jobs("sessiony")
    client.xadd(stream, {"session_id": "sessiony"})
    client.xreadgroup(keys.GROUP, "me", {stream: ">"}, count=1)
    time.sleep(0.6 * TTL_MS / 1000)
    before = time.monotonic()
    assert worker._next_stale_at() - before >= TTL_MS / 2000 - 0.05  # only the half-lease fallback
