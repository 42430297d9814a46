"""Redis capacity: one instance against a 3-shard Redis Cluster, per frame and in sessions at 30 FPS.

Streams RGB-D frames (the bundled ICL 320x240 JPEG + 16-bit depth PNG) from S sessions at 30 FPS through one
gateway and the workers (passthrough engine: the figures are the service's, not the SLAM engine's), first against
one redis-server, then against a cluster of 3 primaries, then 3 primaries + 3 replicas with the gateway waiting for
a replica per frame (all from the bundled binary, loopback TCP).
From every Redis server's INFO before and after it reports, per acked frame: commands the primaries ran (Lua calls
inside scripts included), bytes into and out of the primaries (replication included), and the CPU time of every
server and of the busiest primary. Redis is single-threaded, so one instance saturates at one core: the sessions at
30 FPS one instance carries are 1 s / (its CPU per frame x 30), and a cluster's are the same for its busiest primary
(its CPU over all the frames: the share of sessions it holds counts). On a small machine the gateway and workers
(Python) saturate long before Redis does, so the measured ingest says where this machine stops and the CPU per frame
says where Redis would.

`python -m bench cluster [--sessions 4,16] [--seconds 8] [--workers 2] [--wait-replicas 1] [--write-results]`
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import time
from pathlib import Path

import httpx
import msgpack
import numpy as np
import redis
import websockets

from bench.record import JOURNAL_INBOX
from protocol import keys
from service.launcher import LocalStack
from service.redis_cluster_embedded import EmbeddedRedisCluster
from service.redis_embedded import EmbeddedRedis

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data" / "icl_mini"
RESULTS = JOURNAL_INBOX  # bench/RESULTS.md is generated (python -m bench scoreboard): narrative goes to the journal


def frame_message(seq: int, rgb: bytes, depth: bytes) -> bytes:
    return msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30.0, "image": rgb, "depth": depth})


async def stream_session(ws_url: str, frames: int, fps: float, rgb: bytes, depth: bytes, latencies: list[float],
                         counts: dict[str, int]) -> None:
    """`frames` frames paced at `fps`; an ack's latency is measured from its frame's send."""
    sent_at: dict[int, float] = {}
    async with websockets.connect(ws_url, max_size=None, compression=None) as ws:
        async def read() -> None:
            async for raw in ws:
                message = json.loads(raw)
                if message["type"] == "ack":
                    latencies.append(time.perf_counter() - sent_at.pop(message["seq"]))
                    counts["acked"] += 1
                elif message["type"] == "pose":
                    counts["poses"] += 1
                elif message["type"] == "error":
                    counts[message["code"]] = counts.get(message["code"], 0) + 1
                elif message["type"] == "finished":
                    return

        reader = asyncio.create_task(read())
        start = time.perf_counter()
        for seq in range(frames):
            await asyncio.sleep(max(0.0, start + seq / fps - time.perf_counter()))
            sent_at[seq] = time.perf_counter()
            await ws.send(frame_message(seq, rgb, depth))
        await ws.send(json.dumps({"type": "finish"}))
        await asyncio.wait_for(reader, timeout=300)


def server_counters(clients: list[redis.Redis]) -> dict[str, float]:
    """Commands (those run by scripts included) and bytes in/out summed over the primaries (a primary's output
    includes what it streams to its replicas), CPU seconds over every server, and each server's CPU (`cpu.<port>`)
    and role (`role.<port>`, 1 for a primary)."""
    total = {"calls": 0.0, "bytes_in": 0.0, "bytes_out": 0.0, "cpu_s": 0.0}
    for client in clients:
        info = client.info("all")
        cpu = float(info["used_cpu_sys"]) + float(info["used_cpu_user"])
        total["cpu_s"] += cpu
        total[f"cpu.{info['tcp_port']}"] = cpu
        total[f"role.{info['tcp_port']}"] = 1.0 if info["role"] == "master" else 0.0
        if info["role"] == "master":
            total["calls"] += sum(v["calls"] for k, v in info.items() if k.startswith("cmdstat_")
                                  and k != "cmdstat_info")
            total["bytes_in"] += float(info["total_net_input_bytes"])
            total["bytes_out"] += float(info["total_net_output_bytes"])
    return total


def run_case(stack: LocalStack, servers: list[redis.Redis], sessions: int, seconds: float, rgb: bytes,
             depth: bytes) -> dict:
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        # every frame processed (no live skipping), so that each costs Redis the same
        sids = [api.post("/v1/sessions", json={"name": f"bench-{sessions}", "skip_frames": False}).json()["id"]
                for _ in range(sessions)]
    latencies: list[float] = []
    counts = {"acked": 0, "poses": 0}
    frames = int(seconds * 30)
    before = server_counters(servers)
    t0 = time.perf_counter()

    async def main() -> None:
        await asyncio.gather(*[stream_session(f"{stack.ws_url}/v1/sessions/{sid}/stream", frames, 30.0, rgb, depth,
                                              latencies, counts) for sid in sids])

    asyncio.run(main())
    elapsed = time.perf_counter() - t0
    after = server_counters(servers)
    acked = max(counts["acked"], 1)
    delta = {k: after[k] - before.get(k, 0.0) for k in after if not k.startswith("role.")}
    busiest = max(delta[f"cpu.{k[5:]}"] for k, v in after.items() if k.startswith("role.") and v)
    lat = np.array(latencies) * 1000.0
    return {
        "sessions": sessions, "acked": counts["acked"], "offered": sessions * frames, "poses": counts["poses"],
        "ingest_fps": counts["acked"] / elapsed, "ack_p50_ms": float(np.percentile(lat, 50)),
        "ack_p99_ms": float(np.percentile(lat, 99)), "ops_per_frame": delta["calls"] / acked,
        "kb_in_per_frame": delta["bytes_in"] / acked / 1024, "kb_out_per_frame": delta["bytes_out"] / acked / 1024,
        "cpu_us_per_frame": 1e6 * delta["cpu_s"] / acked,
        # Redis is single-threaded: the busiest primary's core fills first
        "busiest_us_per_frame": 1e6 * busiest / acked,
        "refused": {k: v for k, v in counts.items() if k not in ("acked", "poses")},
    }


def capacity(row: dict) -> float:
    """Sessions at 30 FPS at which the busiest primary spends a whole core (at this run's spread of sessions)."""
    return 1e6 / (row["busiest_us_per_frame"] * 30.0) if row["busiest_us_per_frame"] > 0 else float("inf")


def format_table(rows: list[dict]) -> str:
    lines = ["| Redis | sessions x 30 FPS | frames acked / offered | ingest frames/s | ack p50 / p99 ms | "
             "commands / frame (primaries) | kB in / out per frame (primaries) | Redis CPU us / frame: all servers / "
             "busiest primary | "
             "sessions at 30 FPS the busiest primary carries |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['redis']} | {row['sessions']} | {row['acked']} / {row['offered']} | "
                     f"{row['ingest_fps']:.0f} | {row['ack_p50_ms']:.1f} / {row['ack_p99_ms']:.1f} | "
                     f"{row['ops_per_frame']:.1f} | {row['kb_in_per_frame']:.0f} / {row['kb_out_per_frame']:.0f} | "
                     f"{row['cpu_us_per_frame']:.0f} / {row['busiest_us_per_frame']:.0f} | {capacity(row):.0f} |")
    return "\n".join(lines)


def measure(name: str, url: str, servers: list[redis.Redis], args: argparse.Namespace, rgb: bytes,
            depth: bytes, wait_replicas: int = 0) -> list[dict]:
    env = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LOG_LEVEL": "WARNING", "FLASHMONO_MAX_SESSIONS": "64",
           "FLASHMONO_SNAPSHOT_EVERY": "5"}
    gateway_env = {"FLASHMONO_MAX_QUEUE": "1000", "FLASHMONO_API_KEYS": "",
                   "FLASHMONO_REDIS_WAIT_REPLICAS": str(wait_replicas)}
    rows = []
    with LocalStack(workers=args.workers, redis_url=url, worker_env=env, gateway_env=gateway_env,
                    worker_nice=args.worker_nice) as stack:
        for sessions in args.sessions:
            rows.append({"redis": name, **run_case(stack, servers, sessions, args.seconds, rgb, depth)})
            row = rows[-1]
            print(format_table([row]), flush=True)
    return rows


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench cluster")
    parser.add_argument("--sessions", default="4,16", help="comma-separated session counts")
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--worker-nice", type=int, default=10)
    parser.add_argument("--wait-replicas", type=int, default=1,
                        help="FLASHMONO_REDIS_WAIT_REPLICAS on the cluster with replicas")
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args(argv)
    args.sessions = [int(s) for s in args.sessions.split(",")]
    rgb, depth = (DATA / "rgb" / "00000.jpg").read_bytes(), (DATA / "depth" / "00000.png").read_bytes()
    rows = []
    with EmbeddedRedis(tcp=True) as single:
        rows += measure("1 instance", single.url, [redis.Redis.from_url(single.url)], args, rgb, depth)
    with EmbeddedRedisCluster(masters=3, replicas=0) as cluster:
        rows += measure("cluster, 3 primaries", cluster.url, [n.client() for n in cluster.nodes], args, rgb, depth)
    with EmbeddedRedisCluster(masters=3, replicas=1) as cluster:
        rows += measure(f"cluster, 3 primaries + 3 replicas, WAIT {args.wait_replicas}", cluster.url,
                        [n.client() for n in cluster.nodes], args, rgb, depth, args.wait_replicas)
    table = format_table(rows)
    print(table)
    print(f"load average {os.getloadavg()[0]:.1f}; frame {len(frame_message(0, rgb, depth))} bytes; "
          f"{keys.PARTITIONS} queue partitions")
    return 0
