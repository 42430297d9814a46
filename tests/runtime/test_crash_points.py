"""Crash injection (FLASHMONO_FAILPOINTS) at each step of finishing and of deleting a session: no crash leaves a
session stuck in `finishing`, loses a frame, or leaves a partial ("zombie") record that answers HTTP 500."""

from __future__ import annotations

import json

import httpx
import redis
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack, start_gateway_process
from worker.runtime.failpoints import CRASH_EXIT_CODE

FINISH_STEPS = ("finish:engine", "finish:trajectory", "finish:snapshot", "finish:marked")
FRAMES = 5
ENV = {**WORKER_ENV, "FLASHMONO_LEASE_TTL_MS": "1500", "FLASHMONO_MAX_SESSIONS": "1"}


def session_keys(r: redis.Redis, session_id: str) -> list[bytes]:
    return sorted(r.scan_iter(match=f"*{session_id}*", count=1000))


def test_a_crash_at_each_finish_step_still_finishes_every_session():
    with LocalStack(workers=0, worker_env=ENV) as stack, httpx.Client(base_url=stack.base_url, timeout=30) as api:
        # one worker per step, one session each (a worker takes one session at a time here)
        doomed = [stack.add_worker({"FLASHMONO_FAILPOINTS": step}, worker_id=step) for step in FINISH_STEPS]
        stack.wait_ready(120, need_workers=len(FINISH_STEPS))
        sids = [api.post("/v1/sessions", json={"name": "crash"}).json()["id"] for _ in FINISH_STEPS]
        sockets = [connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) for sid in sids]
        try:
            for ws in sockets:
                for seq in range(FRAMES):
                    ws.send(synthetic_frame(seq))
                ws.send(json.dumps({"type": "finish"}))
            assert [w.wait(timeout=120) for w in doomed] == [CRASH_EXIT_CODE] * len(FINISH_STEPS)
            owners = {api.get(f"/v1/sessions/{sid}").json()["worker"] for sid in sids}
            assert owners == set(FINISH_STEPS)  # every step was crashed at, by the worker of one session
            stack.add_worker({"FLASHMONO_MAX_SESSIONS": "8"}, worker_id="rescuer")
            for ws, sid in zip(sockets, sids):
                messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=120)
                assert messages[-1] == {"type": "finished", "frames": FRAMES}
                session = api.get(f"/v1/sessions/{sid}").json()
                assert session["status"] == "finished" and session["frames_processed"] == FRAMES
                poses = api.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
                assert [p["seq"] for p in poses] == list(range(FRAMES))
                assert api.get(f"/v1/sessions/{sid}/map.ply").status_code == 200
        finally:
            for ws in sockets:
                ws.close()
        r = redis.Redis.from_url(stack.redis_url)
        wait_for(lambda: sum(r.xpending(s, keys.GROUP)["pending"] for s in keys.JOB_STREAMS) == 0, timeout_s=30)


def test_a_crash_at_each_delete_step_leaves_no_zombie():
    gateway_env = {"FLASHMONO_FAILPOINTS": "delete:gateway"}
    with LocalStack(workers=1, worker_env=WORKER_ENV, gateway_env=gateway_env) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=30) as api:
        r = redis.Redis.from_url(stack.redis_url)
        sid = api.post("/v1/sessions", json={"name": "doomed"}).json()["id"]
        # the gateway dies as it starts deleting: the session is whole afterwards, and deletable
        try:
            api.delete(f"/v1/sessions/{sid}")
        except httpx.TransportError:
            pass
        assert stack.gateway.wait(timeout=30) == CRASH_EXIT_CODE
        stack.gateway = start_gateway_process(stack.redis_url, stack.host, stack.port)
        stack.wait_ready(60)
        assert api.get(f"/v1/sessions/{sid}").json()["status"] in ("created", "streaming")
        assert api.delete(f"/v1/sessions/{sid}").status_code == 204
        assert api.get(f"/v1/sessions/{sid}").status_code == 404

        # the worker dies as it notices the deletion (before its own clean-up): nothing of the session remains
        stack.workers[0].terminate()
        stack.workers[0].wait()
        stack.workers.clear()
        stack.add_worker({"FLASHMONO_FAILPOINTS": "delete:worker", "FLASHMONO_PASSTHROUGH_DELAY_MS": "50"})
        stack.wait_ready(120)
        sid = api.post("/v1/sessions", json={"name": "doomed-2"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            for seq in range(20):
                ws.send(synthetic_frame(seq))
            receive_until(ws, lambda m: m["type"] == "pose")
            assert api.delete(f"/v1/sessions/{sid}").status_code == 204
        assert stack.workers[0].wait(timeout=60) == CRASH_EXIT_CODE
        wait_for(lambda: all(k == keys.lease(sid).encode() for k in session_keys(r, sid)), timeout_s=10)
        assert api.get(f"/v1/sessions/{sid}").status_code == 404


def test_create_delete_races_leave_no_record_behind():
    with LocalStack(workers=1, worker_env=WORKER_ENV) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=30) as api:
        r = redis.Redis.from_url(stack.redis_url)
        sids = []
        for _ in range(60):
            sid = api.post("/v1/sessions", json={}).json()["id"]
            assert api.delete(f"/v1/sessions/{sid}").status_code == 204
            sids.append(sid)
        wait_for(lambda: sum(r.xpending(s, keys.GROUP)["pending"] for s in keys.JOB_STREAMS) == 0, timeout_s=60)
        assert [api.get(f"/v1/sessions/{sid}").status_code for sid in sids] == [404] * len(sids)
        leftovers = [k for sid in sids for k in session_keys(r, sid) if k != keys.lease(sid).encode()]
        assert leftovers == []
        assert api.get("/v1/sessions").json()["sessions"] == []
