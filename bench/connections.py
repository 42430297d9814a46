"""Connection benchmark: 1,000 concurrent WebSockets on one gateway (issue 16 point 3).

`--sessions` sessions stream frames; every session has `--streams / --sessions` sockets open on it (one sends, the
others watch its poses). Reports how long the sockets took to open, the gateway's Redis connections (counted by
client name) against the pool size, /readyz polled throughout (how many answers were not 200), ping round trips
and pose delivery on every socket while the senders stream, the refusal of sockets past FLASHMONO_MAX_STREAMS,
and the gateway's resident memory.

`python -m bench connections [--streams 1000] [--sessions 50] [--frames 30] [--write-results]`
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import time
from pathlib import Path

import cv2
import httpx
import msgpack
import numpy as np
import redis
import websockets

from bench.record import JOURNAL_INBOX
from service.launcher import LocalStack

ROOT = Path(__file__).resolve().parent.parent
RESULTS = JOURNAL_INBOX  # bench/RESULTS.md is generated (python -m bench scoreboard): narrative goes to the journal
POOL = 32


def _frame(seq: int, jpeg: bytes) -> bytes:
    return msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30.0, "image": jpeg})


async def _ping(ws) -> float:
    t0 = time.perf_counter()
    await ws.send(json.dumps({"type": "ping"}))
    while json.loads(await ws.recv())["type"] != "pong":
        pass
    return time.perf_counter() - t0


async def _drain_poses(ws, frames: int) -> int:
    poses = 0
    while poses < frames:
        message = json.loads(await asyncio.wait_for(ws.recv(), timeout=120))
        poses += message["type"] == "pose"
    return poses


async def run(stack: LocalStack, streams: int, sessions: int, frames: int) -> dict:
    jpeg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    async with httpx.AsyncClient(base_url=stack.base_url, timeout=60) as api:
        sids = [(await api.post("/v1/sessions", json={"name": f"conn-{i}"})).json()["id"] for i in range(sessions)]
        not_ready, polls, stop = 0, 0, asyncio.Event()

        async def poll_ready() -> None:
            nonlocal not_ready, polls
            while not stop.is_set():
                polls += 1
                not_ready += (await api.get("/readyz")).status_code != 200
                await asyncio.sleep(0.5)

        poller = asyncio.create_task(poll_ready())
        t0 = time.perf_counter()
        sockets = []
        for i in range(streams):  # opened in batches of 100 to keep the accept queue short
            sockets.append(websockets.connect(f"{stack.ws_url}/v1/sessions/{sids[i % sessions]}/stream",
                                              max_size=None, open_timeout=120, ping_interval=None))
        opened = []
        for start in range(0, streams, 100):
            opened += await asyncio.gather(*sockets[start:start + 100])
        open_s = time.perf_counter() - t0
        r = redis.Redis.from_url(stack.redis_url)
        gateway_conns = sum(c.get("name") == "flashmono-gateway" for c in r.client_list())
        rtts = sorted(await asyncio.gather(*(_ping(ws) for ws in opened)))
        refused = []
        for _ in range(3):
            async with websockets.connect(f"{stack.ws_url}/v1/sessions/{sids[0]}/stream") as extra:
                refused.append(json.loads(await asyncio.wait_for(extra.recv(), timeout=30))["code"])
        t1 = time.perf_counter()
        senders = opened[:sessions]
        watchers = [_drain_poses(ws, frames) for ws in opened]
        drain = asyncio.gather(*watchers)
        for seq in range(frames):
            await asyncio.gather(*(ws.send(_frame(seq, jpeg)) for ws in senders))
            await asyncio.sleep(1 / 30)
        delivered = await drain
        deliver_s = time.perf_counter() - t1
        gateway_conns_busy = sum(c.get("name") == "flashmono-gateway" for c in r.client_list())
        stop.set()
        await poller
        rss_mb = _rss_mb(stack.gateway.pid)
        for ws in opened:
            await ws.close()
    return {"streams": len(opened), "open_s": open_s, "gateway_redis_connections": max(gateway_conns,
                                                                                      gateway_conns_busy),
            "pool": POOL, "ping_p50_ms": 1000 * rtts[len(rtts) // 2], "ping_p99_ms": 1000 * rtts[int(len(rtts) * .99)],
            "refused": refused, "poses_delivered": sum(delivered), "poses_expected": frames * len(opened),
            "deliver_s": deliver_s, "sessions": sessions, "frames": frames, "readyz_not_200": not_ready,
            "readyz_polls": polls, "gateway_rss_mb": rss_mb}


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench connections")
    parser.add_argument("--streams", type=int, default=1000)
    parser.add_argument("--sessions", type=int, default=50)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    gateway_env = {"FLASHMONO_MAX_STREAMS": str(args.streams), "FLASHMONO_REDIS_CONNECTIONS": str(POOL)}
    worker_env = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LOG_LEVEL": "WARNING",
                  "FLASHMONO_MAX_SESSIONS": str(args.sessions + 8)}
    with LocalStack(workers=1, gateway_env=gateway_env, worker_env=worker_env) as stack:
        result = asyncio.run(run(stack, args.streams, args.sessions, args.frames))
    result["load_before"] = f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    print(json.dumps(result, indent=1))
    if args.write_results:
        _write(result)
    return 0 if result["poses_delivered"] == result["poses_expected"] and not result["readyz_not_200"] else 1


def _write(result: dict) -> None:
    text = RESULTS.read_text()
    section = (
        f"\n### Connections: {result['streams']} concurrent WebSockets on one gateway (issue 16, `python -m bench "
        f"connections`)\n\n"
        f"2-vCPU CPU machine shared with other jobs (load average before the run: {result['load_before']}); one "
        "gateway, one passthrough worker, embedded Redis; the client in one asyncio process.\n\n"
        "| measure | value |\n|---|---|\n"
        f"| sockets open | {result['streams']} (in {result['open_s']:.1f} s) |\n"
        f"| gateway Redis connections | {result['gateway_redis_connections']} (pool {result['pool']}) |\n"
        f"| ping round trip p50 / p99, all sockets at once | {result['ping_p50_ms']:.0f} / "
        f"{result['ping_p99_ms']:.0f} ms |\n"
        f"| poses delivered to every socket while {result['sessions']} sessions stream {result['frames']} frames "
        f"at 30 FPS | {result['poses_delivered']} of "
        f"{result['poses_expected']} in {result['deliver_s']:.1f} s |\n"
        f"| sockets past FLASHMONO_MAX_STREAMS | {result['refused'].count('too_many_streams')} of "
        f"{len(result['refused'])} refused with too_many_streams (close 1013) |\n"
        f"| /readyz not 200 during the run | {result['readyz_not_200']} of {result['readyz_polls']} polls |\n"
        f"| gateway resident memory | {result['gateway_rss_mb']:.0f} MiB |\n")
    RESULTS.write_text(text.rstrip("\n") + "\n" + section)
