"""A real Redis Cluster (3 primaries + 3 replicas of the bundled redis-server, slots assigned by the test) under the
real gateway and workers: sessions stream, finish, render and are deleted across the shards, each session's keys on
one shard; a primary killed mid-stream fails over to its replica and no acked frame is lost (the gateway waits for
one replica per frame). Also the key layout and the cluster URL on their own, and the one-shot migration of a
single instance's data from the layout before hash tags."""

from __future__ import annotations

import collections
import json
import subprocess
import sys
import time
import uuid

import httpx
import pytest
import redis
from redis.crc import key_slot
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack
from service.redis_cluster_embedded import SLOTS, EmbeddedRedisCluster
from service.redis_embedded import EmbeddedRedis
from worker.runtime.connection import cluster_seeds, is_cluster_url

REPLICATED = {"FLASHMONO_REDIS_WAIT_REPLICAS": "1", "FLASHMONO_REDIS_WAIT_MS": "200"}
RECORDED = {"skip_frames": False}  # every frame processed, even when a loaded machine makes them wait


@pytest.fixture
def cluster():
    with EmbeddedRedisCluster(masters=3, replicas=1) as started:
        yield started


def shard_of(key: str, masters: int = 3) -> int:
    """The primary (by index) that serves `key` when the slots are split evenly, as EmbeddedRedisCluster does."""
    return key_slot(key.encode()) * masters // SLOTS


def stream_frames(ws, seqs) -> None:
    for seq in seqs:
        ws.send(synthetic_frame(seq))


def test_each_session_lives_in_one_slot_and_sessions_and_queues_spread_over_shards():
    ids = [uuid.uuid4().hex for _ in range(300)]
    for sid in ids:
        assert len({key_slot(k.encode()) for k in keys.all_session_keys(sid)}) == 1
        assert keys.jobs(sid) in keys.JOB_STREAMS and keys.requests(sid) in keys.REQUEST_STREAMS
        assert keys.jobs(sid) == keys.jobs(sid)  # stable
    per_shard = collections.Counter(shard_of(keys.session(sid)) for sid in ids)
    assert min(per_shard.values()) > 60  # ~100 each of 300
    for streams in (keys.JOB_STREAMS, keys.REQUEST_STREAMS):
        assert len({key_slot(s.encode()) for s in streams}) == keys.PARTITIONS
        assert len({shard_of(s) for s in streams}) >= 2
    assert len({keys.partition(sid) for sid in ids}) == keys.PARTITIONS


def test_cluster_urls_name_seed_nodes_and_credentials():
    assert is_cluster_url("redis+cluster://h:7000") and is_cluster_url("rediss+cluster://h:7000")
    assert not is_cluster_url("redis://h:6379/0") and not is_cluster_url("unix:///tmp/r.sock")
    assert cluster_seeds("redis+cluster://:secret@h1:7000,h2:7001") == (
        "redis://:secret@h1:7000", [("h1", 7000), ("h2", 7001)])
    assert cluster_seeds("rediss+cluster://h1") == ("rediss://h1:6379", [("h1", 6379)])
    for bad in ("redis+cluster://", "redis+cluster://h1:x", "redis+cluster://h1:7000/3", "redis://h1:7000"):
        with pytest.raises(ValueError):
            cluster_seeds(bad)


def test_gateway_and_workers_serve_sessions_on_every_shard(cluster):
    with LocalStack(workers=2, redis_url=cluster.url, worker_env=WORKER_ENV) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=30) as api:
        sids = [api.post("/v1/sessions", json={**RECORDED, "name": f"c{i}"}).json()["id"] for i in range(6)]
        nodes = {sid: cluster.node_for(keys.session(sid)) for sid in sids}
        assert len({node.port for node in nodes.values()}) >= 2  # the sessions landed on several shards
        with connect(f"{stack.ws_url}/v1/sessions/{sids[0]}/stream", open_timeout=20) as first, \
                connect(f"{stack.ws_url}/v1/sessions/{sids[1]}/stream", open_timeout=20) as second:
            for seq in range(6):  # two sessions at once: the hub reads two hash slots
                stream_frames(first, [seq])
                stream_frames(second, [seq])
            for ws in (first, second):
                ws.send(json.dumps({"type": "finish"}))
                messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
                assert sorted(m["seq"] for m in messages if m["type"] == "pose") == list(range(6))
        for sid in sids[2:]:
            with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
                stream_frames(ws, range(3))
                ws.send(json.dumps({"type": "finish"}))
                receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
        for sid in sids:
            trajectory = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
            assert [p["pose"][3] for p in trajectory] == [float(p["seq"]) for p in trajectory]
            # every key of the session sits on its shard, none elsewhere
            on_shard = nodes[sid].client().keys(f"*{sid}*")
            assert keys.session(sid).encode() in on_shard and keys.poses(sid).encode() in on_shard
            assert all(not n.client().keys(f"*{sid}*") for n in cluster.primaries() if n.port != nodes[sid].port)
        assert {s["id"] for s in api.get("/v1/sessions", params={"limit": 20}).json()["sessions"]} == set(sids)
        # a finished session's render goes through the requests partitions (any worker)
        pose = ",".join(str(float(v)) for v in [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1])
        render = api.get(f"/v1/sessions/{sids[3]}/render",
                         params={"pose": pose, "width": 32, "height": 24, "fx": 30, "fy": 30, "cx": 16, "cy": 12})
        assert render.status_code == 200 and render.content[:4] == b"\x89PNG"
        assert api.delete(f"/v1/sessions/{sids[4]}").status_code == 204
        assert api.get(f"/v1/sessions/{sids[4]}").status_code == 404
        assert nodes[sids[4]].client().keys(f"*{sids[4]}*") == []
        assert api.get("/readyz").json() == {"status": "ready", "redis": True, "workers": 2}


def test_a_primary_killed_mid_stream_fails_over_and_loses_no_acked_frame(cluster):
    frames, kill_at = 40, 15
    env = {**WORKER_ENV, "FLASHMONO_PASSTHROUGH_DELAY_MS": "20"}
    with LocalStack(workers=1, redis_url=cluster.url, worker_env=env, gateway_env=REPLICATED) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=30) as api:
        sid = api.post("/v1/sessions", json={**RECORDED, "name": "failover"}).json()["id"]
        primary = cluster.node_for(keys.session(sid))
        acked: set[int] = set()
        messages: list[dict] = []
        seq = 0
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            while seq < frames:
                if seq == kill_at and primary.alive:
                    cluster.kill(primary)  # the replica takes over after the node timeout (1 s)
                stream_frames(ws, [seq])
                got = receive_until(ws, lambda m, s=seq: m["type"] in ("ack", "error") and m.get("seq") == s,
                                    timeout_s=60)
                messages += got
                if got[-1]["type"] == "ack":
                    acked.add(seq)
                    seq += 1
                    continue
                assert got[-1]["code"] == "unavailable", got[-1]  # refused during the failover: re-send it
                seq = got[-1]["resend_from"]
                time.sleep(0.2)
            ws.send(json.dumps({"type": "finish"}))
            messages += receive_until(ws, lambda m: m["type"] == "finished", timeout_s=120)
        assert acked == set(range(frames))
        promoted = cluster.node_for(keys.session(sid))
        assert promoted.port != primary.port and not primary.alive
        # every acked frame was processed once into the trajectory; a pose message may repeat after a failover
        assert {m["seq"] for m in messages if m["type"] == "pose"} == acked
        trajectory = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
        assert [p["seq"] for p in trajectory] == list(range(frames))
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["status"] == "finished" and session["frames_processed"] == frames
        assert stack.gateway.poll() is None and all(w.poll() is None for w in stack.workers)


def to_legacy_layout(client: redis.Redis, session_ids: list[str]) -> None:
    """Rename a session's keys back to the layout before hash tags, with the old single jobs stream."""
    for sid in session_ids:
        for old, new in keys.legacy_session_keys(sid).items():
            if client.exists(new):
                client.rename(new, old)
    client.delete(*keys.JOB_STREAMS, *keys.REQUEST_STREAMS)
    client.xgroup_create(keys.LEGACY_JOBS, keys.GROUP, id="0", mkstream=True)
    for sid in session_ids:
        client.xadd(keys.LEGACY_JOBS, {"session_id": sid})


def run_migration(url: str) -> str:
    done = subprocess.run([sys.executable, "-m", "worker.runtime.migrate", "--redis-url", url], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_migration_moves_a_single_instance_from_the_old_layout(tmp_path):
    with EmbeddedRedis() as server:
        client = redis.Redis.from_url(server.url)
        with LocalStack(workers=1, redis_url=server.url, worker_env=WORKER_ENV) as stack, \
                httpx.Client(base_url=stack.base_url, timeout=30) as api:
            done = api.post("/v1/sessions", json={**RECORDED, "name": "done"}).json()["id"]
            live = api.post("/v1/sessions", json={**RECORDED, "name": "live"}).json()["id"]
            with connect(f"{stack.ws_url}/v1/sessions/{done}/stream", open_timeout=20) as ws:
                stream_frames(ws, range(4))
                ws.send(json.dumps({"type": "finish"}))
                receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
            with connect(f"{stack.ws_url}/v1/sessions/{live}/stream", open_timeout=20) as ws:
                stream_frames(ws, range(3))
                receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == 2, timeout_s=60)
        to_legacy_layout(client, [done, live])
        assert client.exists(f"fm:session:{done}", f"fm:s:{live}:in") == 2
        assert run_migration(server.url).startswith("moved ")
        assert not client.exists(f"fm:session:{done}", f"fm:s:{live}:in", keys.LEGACY_JOBS)
        assert run_migration(server.url).startswith("moved 0 keys of 0 sessions")  # nothing left to move
        with LocalStack(workers=1, redis_url=server.url, worker_env=WORKER_ENV) as stack, \
                httpx.Client(base_url=stack.base_url, timeout=30) as api:
            assert len(api.get(f"/v1/sessions/{done}/trajectory").json()["poses"]) == 4
            assert api.get(f"/v1/sessions/{live}").json()["status"] == "streaming"
            with connect(f"{stack.ws_url}/v1/sessions/{live}/stream", open_timeout=20) as ws:
                stream_frames(ws, range(3, 6))  # the live session resumes on the new layout
                ws.send(json.dumps({"type": "finish"}))
                receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
            wait_for(lambda: api.get(f"/v1/sessions/{live}").json()["status"] == "finished", timeout_s=30)
            assert [p["seq"] for p in api.get(f"/v1/sessions/{live}/trajectory").json()["poses"]] == list(range(6))
