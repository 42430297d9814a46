"""Many open WebSockets on one gateway: bounded Redis connections (one reader serves every stream's results), a
clear refusal past FLASHMONO_MAX_STREAMS, /readyz true throughout, and every stream still gets its poses."""

from __future__ import annotations

import asyncio
import json

import httpx
import msgpack
import redis
import websockets

from service.launcher import LocalStack

STREAMS = 60
POOL = 8
WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LOG_LEVEL": "WARNING", "FLASHMONO_MAX_SESSIONS": "64"}


def frame(seq: int) -> bytes:
    import cv2
    import numpy as np

    jpeg = cv2.imencode(".jpg", np.zeros((24, 32, 3), np.uint8))[1].tobytes()
    return msgpack.packb({"type": "frame", "seq": seq, "timestamp": 0.0, "image": jpeg})


async def until(ws, kind: str) -> dict:
    while True:
        message = json.loads(await asyncio.wait_for(ws.recv(), timeout=60))
        if message["type"] == kind:
            return message


def test_many_streams_share_a_bounded_pool_and_the_next_is_refused():
    gateway_env = {"FLASHMONO_MAX_STREAMS": str(STREAMS), "FLASHMONO_REDIS_CONNECTIONS": str(POOL)}
    with LocalStack(workers=1, worker_env=WORKER_ENV, gateway_env=gateway_env) as stack, \
            httpx.Client(base_url=stack.base_url, timeout=30) as api:
        sids = [api.post("/v1/sessions", json={}).json()["id"] for _ in range(STREAMS)]
        r = redis.Redis.from_url(stack.redis_url)

        def gateway_connections() -> int:
            return sum(c.get("name") == "flashmono-gateway" for c in r.client_list())

        async def scenario() -> tuple[list[dict], dict, int, int]:
            sockets = [await websockets.connect(f"{stack.ws_url}/v1/sessions/{sid}/stream") for sid in sids]
            try:
                for ws in sockets:
                    await ws.send(frame(0))
                poses = await asyncio.gather(*(until(ws, "pose") for ws in sockets))
                ready = await asyncio.to_thread(api.get, "/readyz")
                clients = gateway_connections()
                async with websockets.connect(f"{stack.ws_url}/v1/sessions/{sids[0]}/stream") as extra:
                    refusal = json.loads(await asyncio.wait_for(extra.recv(), timeout=30))
                    await asyncio.wait_for(extra.wait_closed(), timeout=30)
                    code = extra.close_code
                return poses, refusal | {"ready": ready.status_code, "clients": clients}, code, len(sockets)
            finally:
                for ws in sockets:
                    await ws.close()

        poses, refusal, code, opened = asyncio.run(scenario())
        assert opened == STREAMS and all(p["seq"] == 0 for p in poses)
        assert refusal["code"] == "too_many_streams" and f"{STREAMS} open streams" in refusal["message"]
        assert code == 1013
        assert refusal["ready"] == 200
        assert 1 <= refusal["clients"] <= POOL  # the gateway's connections, whatever the number of streams
