"""Several sessions per worker, several workers per Redis; leases; snapshots every N keyframes; XACK after store."""

from __future__ import annotations

import collections
import contextlib
import json
import time

import httpx
import pytest
import redis
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack
from service.redis_embedded import EmbeddedRedis
from worker.runtime.leases import Leases, lease_holder


def test_sessions_spread_over_workers_each_owned_by_one():
    env = {**WORKER_ENV, "FLASHMONO_MAX_SESSIONS": "2"}
    with LocalStack(workers=2, worker_env=env) as stack, httpx.Client(base_url=stack.base_url) as api:
        r = redis.Redis.from_url(stack.redis_url)
        sids = [api.post("/v1/sessions", json={"device_id": f"d{i}"}).json()["id"] for i in range(4)]
        with contextlib.ExitStack() as opened:
            sockets = [opened.enter_context(connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20))
                       for sid in sids]
            for ws in sockets:  # a session takes a worker slot once its first frame is in
                ws.send(synthetic_frame(0))
            owners = wait_for(lambda: [lease_holder(r, sid) for sid in sids] if all(
                lease_holder(r, sid) for sid in sids) else None)
            assert sorted(collections.Counter(owners).values()) == [2, 2]  # 2 workers x 2 sessions each
            for seq in range(1, 10):  # interleaved: all four sessions stream at once
                for ws in sockets:
                    ws.send(synthetic_frame(seq))
            for ws in sockets:
                ws.send(json.dumps({"type": "finish"}))
            for ws in sockets:
                messages = receive_until(ws, lambda m: m["type"] == "finished")
                assert sorted(m["seq"] for m in messages if m["type"] == "pose") == list(range(10))
        for sid, owner in zip(sids, owners):
            session = api.get(f"/v1/sessions/{sid}").json()
            assert session["worker"] == owner and session["frames_processed"] == 10
            # passthrough: keyframes at seq 0, 4, 8; snapshots every 2 keyframes (seq 4), then the final one
            assert session["keyframes"] == 3
            assert int(r.hget(keys.snapshot(sid), "seq")) == 9
            assert r.xpending(keys.inbox(sid), keys.GROUP)["pending"] == 0  # every frame acked after its result
            assert r.xlen(keys.inbox(sid)) <= 1  # acknowledged frames covered by a snapshot are trimmed
            assert r.get(keys.lease(sid)) is None  # released once finished

        def engine_counts() -> list[float] | None:
            """Per-worker engine event counts once both workers have published all of them (on their heartbeat,
            which a loaded machine may delay past the first publication: wait for the total)."""
            text = httpx.get(f"{stack.base_url}/metrics").text
            counts = [float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                      if line.startswith("flashmono_worker_stage_events_total") and 'stage="engine"' in line]
            return counts if len(counts) == 2 and all(c > 0 for c in counts) and sum(counts) >= 40 else None

        assert sum(wait_for(engine_counts, timeout_s=20)) == 40  # both workers report their stage timings


def test_lease_acquire_renew_release_and_expiry():
    with EmbeddedRedis() as server:
        client = redis.Redis.from_url(server.url)
        a, b = Leases(client, "a", ttl_ms=300), Leases(client, "b", ttl_ms=300)
        assert a.acquire("s1") and not b.acquire("s1")
        assert a.renew("s1") and not b.renew("s1")
        b.release("s1")  # not b's lease: nothing happens
        assert lease_holder(client, "s1") == "a"
        time.sleep(0.45)  # a stops heartbeating: the lease expires
        assert lease_holder(client, "s1") is None
        assert b.acquire("s1") and not a.renew("s1")
        b.release("s1")
        assert lease_holder(client, "s1") is None
        with pytest.raises(ValueError):
            Leases(client, "c", ttl_ms=10)
