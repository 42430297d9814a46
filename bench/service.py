"""Service benchmark: 1, 8 and 32 concurrent sessions streaming 320x240 JPEG at 30 FPS through one gateway,
plus an unthrottled run for the gateway's ingest capacity.

Reports ingest frames/s, ack latency p50/p99 (client-measured: frame sent -> ack received) and the workers'
dispatch overhead per frame beyond the engine's compute (decode + atomic result store; measured inside the worker).
The workers run the passthrough engine so the figures are the service's own, not the SLAM engine's.

`python -m bench service [--seconds S] [--workers N] [--write-results]`
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

from bench.record import JOURNAL_INBOX, Recorder
from protocol import keys
from service.launcher import LocalStack

ROOT = Path(__file__).resolve().parent.parent
FRAME = ROOT / "tests" / "data" / "icl_mini" / "rgb" / "00000.jpg"
RESULTS = JOURNAL_INBOX  # bench/RESULTS.md is generated (python -m bench scoreboard): narrative goes to the journal


async def stream_session(ws_url: str, frames: int, fps: float | None, jpeg: bytes, latencies: list[float],
                         counts: dict[str, int]) -> tuple[float, float]:
    """Stream `frames` frames (paced at `fps`, or as fast as acks allow with a window of 16); (first send, last ack)."""
    sent_at: dict[int, float] = {}
    window = asyncio.Semaphore(16)
    async with websockets.connect(ws_url, max_size=None, compression=None) as ws:
        last_ack = 0.0

        async def read() -> None:
            nonlocal last_ack
            async for raw in ws:
                message = json.loads(raw)
                kind = message["type"]
                if kind == "ack":
                    last_ack = time.perf_counter()
                    latencies.append(last_ack - sent_at.pop(message["seq"]))
                    counts["acked"] += 1
                    if fps is None:
                        window.release()
                elif kind == "error":
                    counts[message["code"]] = counts.get(message["code"], 0) + 1
                    if message.get("seq") in sent_at:
                        sent_at.pop(message["seq"])
                        if fps is None:
                            window.release()
                elif kind == "pose":
                    counts["poses"] += 1
                elif kind == "finished":
                    return

        reader = asyncio.create_task(read())
        start = time.perf_counter()
        for seq in range(frames):
            if fps is not None:
                await asyncio.sleep(max(0.0, start + seq / fps - time.perf_counter()))
            else:
                await window.acquire()
            sent_at[seq] = time.perf_counter()
            await ws.send(msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30.0, "image": jpeg}))
        await ws.send(json.dumps({"type": "finish"}))
        await asyncio.wait_for(reader, timeout=600)
    return start, last_ack


def worker_dispatch(client: redis.Redis) -> dict[str, float]:
    """Summed stage figures over all workers: dispatch sum/count and the worst recent p50/p99."""
    totals = {"sum": 0.0, "count": 0.0, "p50": 0.0, "p99": 0.0, "engine_sum": 0.0, "engine_count": 0.0,
              "cpu_sum": 0.0}
    for key in client.scan_iter(match=f"{keys.WORKER_STATS_PREFIX}*"):
        stats = {k.decode(): float(v) for k, v in client.hgetall(key).items()}
        totals["sum"] += stats.get("dispatch_sum", 0.0)
        totals["count"] += stats.get("dispatch_count", 0.0)
        totals["engine_sum"] += stats.get("engine_sum", 0.0)
        totals["cpu_sum"] += stats.get("dispatch_cpu_sum", 0.0)
        totals["engine_count"] += stats.get("engine_count", 0.0)
        totals["p50"] = max(totals["p50"], stats.get("dispatch_p50", 0.0))
        totals["p99"] = max(totals["p99"], stats.get("dispatch_p99", 0.0))
    return totals


def run_case(stack: LocalStack, sessions: int, frames: int, fps: float | None, jpeg: bytes) -> dict:
    r = redis.Redis.from_url(stack.redis_url)
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sids = [api.post("/v1/sessions", json={"name": f"bench-{sessions}"}).json()["id"] for _ in range(sessions)]
    time.sleep(1.5)  # let the workers take the sessions
    before = worker_dispatch(r)
    latencies: list[float] = []
    counts = {"acked": 0, "poses": 0}

    async def main() -> list[tuple[float, float]]:
        return await asyncio.gather(*[
            stream_session(f"{stack.ws_url}/v1/sessions/{sid}/stream", frames, fps, jpeg, latencies, counts)
            for sid in sids])

    spans = asyncio.run(main())
    time.sleep(1.0)  # one heartbeat: the workers publish their stage figures
    after = worker_dispatch(r)
    elapsed = max(end for _, end in spans) - min(start for start, _ in spans)
    n = after["count"] - before["count"]
    lat = np.array(latencies) * 1000.0
    return {
        "sessions": sessions, "fps_per_session": fps or "max", "frames_acked": counts["acked"],
        "poses": counts["poses"], "refused": {k: v for k, v in counts.items() if k not in ("acked", "poses")},
        "ingest_fps": counts["acked"] / elapsed if elapsed > 0 else 0.0,
        "ack_p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "ack_p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "dispatch_mean_ms": 1000.0 * (after["sum"] - before["sum"]) / n if n else float("nan"),
        "dispatch_p99_ms": 1000.0 * after["p99"],
        "dispatch_cpu_ms": 1000.0 * (after["cpu_sum"] - before["cpu_sum"]) / n if n else float("nan"),
        "engine_mean_ms": 1000.0 * (after["engine_sum"] - before["engine_sum"]) / n if n else float("nan"),
    }


def format_table(rows: list[dict]) -> str:
    lines = ["| sessions | offered FPS/session | frames acked | ingest frames/s | ack p50 ms | ack p99 ms | "
             "dispatch mean ms | dispatch p99 ms | dispatch CPU ms | refused |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for row in rows:
        lines.append(f"| {row['sessions']} | {row['fps_per_session']} | {row['frames_acked']} | "
                     f"{row['ingest_fps']:.0f} | {row['ack_p50_ms']:.2f} | {row['ack_p99_ms']:.2f} | "
                     f"{row['dispatch_mean_ms']:.2f} | {row['dispatch_p99_ms']:.2f} | {row['dispatch_cpu_ms']:.2f} | "
                     f"{row['refused'] or '-'} |")
    return "\n".join(lines)


def write_results(table: str, notes: str) -> None:
    """Replace (or append) the "## Service" section of the journal's inbox, leaving the others untouched."""
    text = RESULTS.read_text()
    section = f"## Service\n\n{notes}\n\n{table}\n"
    start = text.find("\n## Service\n")
    if start < 0:
        text = text.rstrip("\n") + "\n\n" + section
    else:
        end = text.find("\n## ", start + 1)
        text = text[:start + 1] + section + (text[end:] if end >= 0 else "")
    RESULTS.write_text(text)


RECORDED = ("ingest_fps", "ack_p50_ms", "ack_p99_ms", "dispatch_mean_ms", "dispatch_p99_ms", "frames_acked")


def service_case(row: dict, workers: int) -> dict:
    """A row's case: sessions and their frame rate ("max": unthrottled), on N passthrough workers."""
    rate = "unthrottled" if row["fps_per_session"] == "max" else f"{row['fps_per_session']:g} FPS"
    return {"area": "service", "sequence": f"{workers} passthrough worker{'s' * (workers > 1)}",
            "mode": f"{row['sessions']} sessions, {rate}"}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench service")
    parser.add_argument("--seconds", type=float, default=5.0, help="streaming time of the 30 FPS runs")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--max-frames", type=int, default=100, help="frames per session in the unthrottled run")
    parser.add_argument("--worker-nice", type=int, default=0,
                        help="run the workers at this nice level: on a shared box the gateway's ingest path then "
                             "gets the CPU first, as it would with the workers on their own (GPU) machines")
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args(argv)
    jpeg = FRAME.read_bytes()
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (240, 320, 3)
    env = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LOG_LEVEL": "WARNING", "FLASHMONO_MAX_SESSIONS": "64",
           "FLASHMONO_SNAPSHOT_EVERY": "5"}
    gateway_env = {"FLASHMONO_MAX_QUEUE": "1000", "FLASHMONO_API_KEYS": ""}
    recorder = Recorder("service", argv)
    rows = []
    with LocalStack(workers=args.workers, worker_env=env, gateway_env=gateway_env,
                    worker_nice=args.worker_nice) as stack:
        frames = int(args.seconds * 30)
        for sessions in (1, 8, 32):
            rows.append(run_case(stack, sessions, frames, 30.0, jpeg))
            print(format_table(rows[-1:]), flush=True)
        rows.append(run_case(stack, 32, args.max_frames, None, jpeg))
        print(format_table(rows[-1:]), flush=True)
    load = os.getloadavg()[0]
    table = format_table(rows)
    print(table)
    if args.write_results:
        notes = (f"`python -m bench service --workers {args.workers} --seconds {args.seconds:g} --write-results`: "
                 f"one gateway (uvicorn, 1 process), {args.workers} worker(s) with the passthrough engine "
                 f"(nice {args.worker_nice}), "
                 f"embedded redis-server on a unix socket, clients in one asyncio process; 320x240 JPEG "
                 f"({len(jpeg)} bytes) per frame. All on the 2-vCPU development machine (load average "
                 f"{load:.1f} at the end: shared with other work). \"max\" = 32 sessions streaming unthrottled "
                 f"(16 frames in flight each). Dispatch = worker time per frame outside the engine (JPEG decode, "
                 f"atomic result store + XACK) in wall time; dispatch CPU = the same stages in the thread's own "
                 f"CPU time (without waits for a core or the GIL); waiting for Redis reads is not included.")
        write_results(table, notes)
        for row in rows:
            recorder.write(service_case(row, args.workers), {k: row[k] for k in RECORDED})
    return 0
