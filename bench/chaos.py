"""Chaos benchmark (issue 16 point 9): 8 concurrent SDK streams while, one after the other, a worker is SIGKILLed,
the gateway is SIGKILLed and restarted, the gateway is stopped (SIGSTOP) for 10 s, and Redis is SIGKILLed and
restarted on its append-only file after a 60 s outage.

Reports, per event, the recovery time (event over -> every stream has received a new pose) and, at the end, the
frames the clients had acknowledged against the frames in the sessions' final trajectories (lost = acknowledged
but missing; duplicates cannot exist: the trajectory is keyed by seq).

`python -m bench chaos [--streams 8] [--fps 10] [--outage-s 60] [--stall-s 10] [--write-results]`

`--takeovers N` instead kills the worker owning one stream N times (a standby worker takes over; the killed one is
replaced) with the production lease (2.5 s) and reports, per kill, the gap until poses resume and where it went
(the new owner's timeline: job claimed, lease taken, restored, replayed, first pose), with the passthrough engine
so that the runtime's own share shows.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.record import JOURNAL_INBOX
from client.async_sdk import AsyncFlashMonoClient
from client.models import PoseEvent
from client.streaming import WireOptions
from service.launcher import LocalStack, start_gateway_process
from service.redis_embedded import EmbeddedRedis
from worker.data.frame import Frame

RESULTS = JOURNAL_INBOX  # bench/RESULTS.md is generated (python -m bench scoreboard): narrative goes to the journal
WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_PASSTHROUGH_DELAY_MS": "10",
              "FLASHMONO_LEASE_TTL_MS": "5000", "FLASHMONO_SNAPSHOT_EVERY": "4", "FLASHMONO_LOG_LEVEL": "WARNING"}


def _frame(index: int) -> Frame:
    pose = np.eye(4)
    pose[0, 3] = float(index)
    return Frame(index=index, timestamp=index / 30.0, image=np.full((48, 64, 3), index % 256, np.uint8), pose=pose)


class Chaos:
    """The stack, its Redis, and the events done to them (each returns once the fault is over)."""

    def __init__(self, stack: LocalStack, redis: EmbeddedRedis) -> None:
        self.stack = stack
        self.redis = redis

    async def kill_worker(self) -> None:
        victim = self.stack.workers.pop(0)
        victim.send_signal(signal.SIGKILL)
        victim.wait()
        self.stack.add_worker()  # what `flashmono serve`'s supervisor does

    async def kill_gateway(self) -> None:
        self.stack.gateway.send_signal(signal.SIGKILL)
        self.stack.gateway.wait()
        await asyncio.sleep(1.0)
        self.stack.gateway = start_gateway_process(self.stack.redis_url, self.stack.host, self.stack.port)

    async def stall_gateway(self, seconds: float) -> None:
        self.stack.gateway.send_signal(signal.SIGSTOP)
        await asyncio.sleep(seconds)
        self.stack.gateway.send_signal(signal.SIGCONT)

    async def kill_redis(self, outage_s: float) -> None:
        self.redis.kill()
        await asyncio.sleep(outage_s)
        await asyncio.to_thread(self.redis.start)


async def _stream(client: AsyncFlashMonoClient, session_id: str, fps: float, stop: asyncio.Event,
                  pose_times: list[float]) -> dict:
    def on_event(event) -> None:
        if isinstance(event, PoseEvent):
            pose_times.append(time.monotonic())

    async with client.open_stream(session_id, wire=WireOptions(send_pose=True, send_intrinsics=False),
                                  on_event=on_event, reconnect_s=180, max_retries=1000,
                                  idle_timeout_s=600) as stream:
        index = 0
        start = time.monotonic()
        while not stop.is_set():
            await stream.send(_frame(index))
            index += 1
            await asyncio.sleep(max(0.0, start + index / fps - time.monotonic()))
        summary = await stream.finish(timeout_s=600)
        return {"sent": index, "acked": sorted(stream.flow.accepted), "reconnects": summary.reconnects,
                "errors": len(summary.errors)}


async def run(stack: LocalStack, redis: EmbeddedRedis, streams: int, fps: float, outage_s: float,
              stall_s: float, settle_s: float = 8.0) -> dict:
    chaos = Chaos(stack, redis)
    events = [("worker SIGKILL", chaos.kill_worker), ("gateway SIGKILL + restart", chaos.kill_gateway),
              (f"gateway SIGSTOP {stall_s:g} s", lambda: chaos.stall_gateway(stall_s)),
              (f"Redis SIGKILL, {outage_s:g} s outage, restart", lambda: chaos.kill_redis(outage_s))]
    async with AsyncFlashMonoClient(stack.base_url, timeout_s=120) as client:
        sids = [(await client.create_session(name=f"chaos-{i}")).id for i in range(streams)]
        stop = asyncio.Event()
        pose_times: list[list[float]] = [[] for _ in sids]
        tasks = [asyncio.create_task(_stream(client, sid, fps, stop, pose_times[i])) for i, sid in enumerate(sids)]
        recoveries = []
        await asyncio.sleep(settle_s)
        for name, event in events:
            t0 = time.monotonic()
            await event()
            over = time.monotonic()
            deadline = over + 300
            while time.monotonic() < deadline and not all(t and t[-1] > over for t in pose_times):
                await asyncio.sleep(0.05)
            recovered = all(t and t[-1] > over for t in pose_times)
            first = [next((x for x in t if x > over), float("inf")) for t in pose_times]
            recoveries.append({"event": name, "fault_s": over - t0,
                               "recovery_s": max(first) - over if recovered else None})
            print(json.dumps(recoveries[-1]), flush=True)
            await asyncio.sleep(settle_s)
        stop.set()
        outcomes = await asyncio.gather(*tasks)
        lost = missing_total = acked_total = 0
        for sid, outcome in zip(sids, outcomes):
            trajectory = await client.trajectory(sid)
            seqs = {p.seq for p in trajectory.poses}
            wrong = sum(1 for p in trajectory.poses if p.pose[0, 3] != p.seq)
            lost += len(set(outcome["acked"]) - seqs) + wrong
            acked_total += len(outcome["acked"])
            missing_total += outcome["sent"] - len(seqs)
    return {"streams": streams, "fps": fps, "recoveries": recoveries, "acked": acked_total,
            "lost": lost, "sent": sum(o["sent"] for o in outcomes), "not_in_trajectory": missing_total,
            "reconnects": sum(o["reconnects"] for o in outcomes), "frame_errors": sum(o["errors"] for o in outcomes),
            "processes_alive": stack.gateway.poll() is None and all(w.poll() is None for w in stack.workers)}


async def takeovers(stack: LocalStack, kills: int, fps: float, settle_s: float = 6.0) -> dict:
    """Kill the owner of one stream `kills` times; per kill the pose gap and the new owner's phases."""
    import redis as redis_client

    from bench.takeover import process_of, takeover_phases
    from protocol import keys

    r = redis_client.Redis.from_url(stack.redis_url)
    rows = []
    async with AsyncFlashMonoClient(stack.base_url, timeout_s=120) as client:
        sid = (await client.create_session(name="takeovers")).id
        stop = asyncio.Event()
        pose_times: list[float] = []
        task = asyncio.create_task(_stream(client, sid, fps, stop, pose_times))
        await asyncio.sleep(settle_s)
        for _ in range(kills):
            await asyncio.to_thread(stack.wait_ready, 300, len(stack.workers))
            r.hdel(keys.session(sid), "takeover")
            owner = r.get(keys.lease(sid)).decode()  # the lease holder: the owner right now
            victim = process_of(owner, stack.workers)
            killed, killed_wall = time.monotonic(), time.time()
            victim.send_signal(signal.SIGKILL)
            await asyncio.to_thread(victim.wait)
            stack.workers.remove(victim)
            stack.add_worker()
            deadline = killed + 120
            while time.monotonic() < deadline and not (pose_times and pose_times[-1] > killed):
                await asyncio.sleep(0.02)
            gap = next((t - killed for t in pose_times if t > killed), None)
            await asyncio.sleep(0.5)
            rows.append({"gap_s": gap, **(takeover_phases(stack.redis_url, sid, killed_wall) or {})})
            print(json.dumps(rows[-1]), flush=True)
            await asyncio.sleep(settle_s)
        stop.set()
        outcome = await task
        trajectory = await client.trajectory(sid)
        seqs = {p.seq for p in trajectory.poses}
        lost = len(set(outcome["acked"]) - seqs) + sum(1 for p in trajectory.poses if p.pose[0, 3] != p.seq)
    r.close()
    gaps = [row["gap_s"] for row in rows if row["gap_s"] is not None and row.get("worker")]
    claims = [row["claimed_after_kill_s"] for row in rows if row.get("claimed_after_kill_s") is not None]
    return {"kills": kills, "fps": fps, "takeovers": rows, "lost": lost, "acked": len(outcome["acked"]),
            "gap_s": {"median": float(np.median(gaps)) if gaps else None, "max": max(gaps, default=None)},
            "claimed_after_kill_s": {"median": float(np.median(claims)) if claims else None,
                                     "max": max(claims, default=None)}}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench chaos")
    parser.add_argument("--takeovers", type=int, default=0,
                        help="only kill the owner of one stream this many times and time each takeover")
    parser.add_argument("--streams", type=int, default=8)
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--outage-s", type=float, default=60.0)
    parser.add_argument("--stall-s", type=float, default=10.0)
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    if args.takeovers:
        env = {**WORKER_ENV, "FLASHMONO_LEASE_TTL_MS": "2500"}
        with LocalStack(workers=2, worker_env=env) as stack:
            result = asyncio.run(takeovers(stack, args.takeovers, args.fps))
        result["load"] = f"{load[0]:.1f} -> {os.getloadavg()[0]:.1f}"
        print(json.dumps(result, indent=1))
        return 0 if result["lost"] == 0 else 1
    with tempfile.TemporaryDirectory(prefix="flashmono-chaos-") as data:
        redis = EmbeddedRedis(data_dir=Path(data) / "redis").start()
        try:
            with LocalStack(workers=2, redis_url=redis.url, worker_env=WORKER_ENV) as stack:
                result = asyncio.run(run(stack, redis, args.streams, args.fps, args.outage_s, args.stall_s))
        finally:
            redis.stop()
    result["load_before"] = f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    result["load_after"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(json.dumps(result, indent=1))
    if args.write_results:
        _write(result)
    return 0 if result["lost"] == 0 and all(r["recovery_s"] is not None for r in result["recoveries"]) else 1


def _write(result: dict) -> None:
    def recovery(r: dict) -> str:
        return "not recovered" if r["recovery_s"] is None else f"{r['recovery_s']:.1f} s"

    rows = "".join(f"| {r['event']} | {r['fault_s']:.1f} s | {recovery(r)} |\n" for r in result["recoveries"])
    section = (
        f"\n### Chaos: {result['streams']} SDK streams at {result['fps']:g} FPS through four faults "
        "(`python -m bench chaos`)\n\n"
        f"2-vCPU CPU machine shared with other jobs (load average {result['load_before']} before, "
        f"{result['load_after']} after); one gateway, two passthrough workers (a killed one is replaced at once, as "
        "`flashmono serve`'s supervisor does), embedded Redis with its append-only file. Recovery: from the end of "
        "the fault until every stream has received a new pose.\n\n"
        "| fault | fault lasted | recovery |\n|---|---|---|\n" + rows +
        f"\nFrames the clients had acknowledged: {result['acked']}; acknowledged but missing from the final "
        f"trajectories (or under the wrong seq): **{result['lost']}**. Frames sent: {result['sent']}; not in a "
        f"trajectory: {result['not_in_trajectory']}. Reconnects by the SDK: {result['reconnects']}; per-frame "
        f"errors reported: {result['frame_errors']}; every process alive at the end: {result['processes_alive']}.\n")
    RESULTS.write_text(RESULTS.read_text().rstrip("\n") + "\n" + section)
