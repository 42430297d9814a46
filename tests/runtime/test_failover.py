"""kill -9 a worker mid-stream: another worker claims the session when the lease expires, restores the snapshot,
replays the frames after it, and finishes with every frame seq processed and reported exactly once."""

from __future__ import annotations

import collections
import json
import signal

import httpx
import pytest
import redis
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack

FRAMES = 40
MAX_QUEUE = 40


@pytest.fixture(scope="module")
def stack():
    """No worker at first (frames queue up deterministically); the tests add workers."""
    slow = {**WORKER_ENV, "FLASHMONO_PASSTHROUGH_DELAY_MS": "60"}
    with LocalStack(workers=0, worker_env=slow, gateway_env={"FLASHMONO_MAX_QUEUE": str(MAX_QUEUE)}) as local:
        yield local


def test_full_queue_refuses_frames_with_backpressure_errors(stack):
    with httpx.Client(base_url=stack.base_url) as api:
        sid = api.post("/v1/sessions", json={"name": "backpressure"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            replies = []
            for seq in range(MAX_QUEUE + 3):
                ws.send(synthetic_frame(seq))
                replies += receive_until(ws, lambda m: m["type"] in ("ack", "error"))
            assert [(m["seq"], m["queue_depth"]) for m in replies[:MAX_QUEUE]] == [
                (seq, seq + 1) for seq in range(MAX_QUEUE)]
            refused = replies[MAX_QUEUE:]
            assert [(m["type"], m["code"], m["seq"], m["queue_depth"]) for m in refused] == [
                ("error", "backpressure", seq, MAX_QUEUE) for seq in range(MAX_QUEUE, MAX_QUEUE + 3)]
            assert "resend" in refused[0]["message"]
            ws.send(synthetic_frame(MAX_QUEUE + 3))  # still refused: nothing consumed the queue
            assert receive_until(ws, lambda m: m["type"] in ("ack", "error"))[-1]["code"] == "backpressure"
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["frames_received"] == MAX_QUEUE and session["status"] == "streaming"
        assert api.delete(f"/v1/sessions/{sid}").status_code == 204


def test_worker_killed_mid_stream_is_replaced_without_loss_or_duplicates(stack):
    with httpx.Client(base_url=stack.base_url) as api:
        r = redis.Redis.from_url(stack.redis_url)
        first = stack.add_worker(worker_id="worker-a")
        stack.wait_ready(180, need_workers=1)
        sid = api.post("/v1/sessions", json={"name": "failover"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            for seq in range(FRAMES):
                ws.send(synthetic_frame(seq))
            ws.send(json.dumps({"type": "finish"}))
            messages = receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] >= 12)
            # a chunked snapshot exists before the crash: its sealed poses are in the chunks hash, not in the blob
            wait_for(lambda: int(r.hget(keys.snapshot(sid), "seq") or 0) >= 8)
            first.send_signal(signal.SIGKILL)
            first.wait()
            processed_at_kill = int(r.hget(keys.session(sid), "frames_processed"))
            snapshot_seq = int(r.hget(keys.snapshot(sid), "seq"))
            assert 0 < processed_at_kill < FRAMES
            assert r.get(keys.lease(sid)) == b"worker-a"  # the dead worker's lease is still there, until it expires
            manifest = json.loads(r.hget(keys.snapshot(sid), "chunks"))
            assert manifest["sealed"] >= 1 and r.hlen(keys.snapshot_chunks(sid)) == manifest["sealed"]
            stack.add_worker(worker_id="worker-b")
            messages += receive_until(ws, lambda m: m["type"] == "finished", timeout_s=180)
        poses = [m for m in messages if m["type"] == "pose"]
        counts = collections.Counter(p["seq"] for p in poses)
        assert sorted(counts) == list(range(FRAMES)) and set(counts.values()) == {1}
        assert all(p["pose"][3] == p["seq"] for p in poses)  # each pose belongs to its own frame
        assert messages[-1] == {"type": "finished", "frames": FRAMES}
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["status"] == "finished" and session["worker"] == "worker-b"
        # worker-b took over from that snapshot (restored, replayed what came after it, then answered frames)
        takeover = json.loads(r.hget(keys.session(sid), "takeover"))
        assert takeover["worker"] == "worker-b" and takeover["snapshot_seq"] == snapshot_seq
        assert takeover["started_at"] <= takeover["restored_at"] <= takeover["first_pose_at"]
        assert takeover["first_pose_seq"] > snapshot_seq
        assert session["frames_received"] == session["frames_processed"] == FRAMES
        trajectory = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
        assert [p["seq"] for p in trajectory] == list(range(FRAMES))
        # the restored engine saw every frame: its final snapshot holds the full trajectory
        assert int(r.hget(keys.snapshot(sid), "seq")) == FRAMES - 1 and snapshot_seq < FRAMES - 1
        assert r.xpending(keys.inbox(sid), keys.GROUP)["pending"] == 0
        # the job entry is acknowledged when the worker reaps the finished session's runner (its next loop turn)
        wait_for(lambda: sum(r.xpending(s, keys.GROUP)["pending"] for s in keys.JOB_STREAMS) == 0, timeout_s=20)
        assert api.get(f"/v1/sessions/{sid}/map.ply").content.count(b"\n") == FRAMES + 7  # header + one per frame
