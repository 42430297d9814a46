"""Killing a session's owning worker and reading where the takeover's time went: shared by `bench live --kill-at`,
`bench chaos` and `bench sdk_failover`.
"""

from __future__ import annotations

import asyncio
import json
import signal
import time
from collections.abc import Callable
from typing import Any


def process_of(worker_id: str | None, processes: list) -> Any:
    """The worker process whose id (`host-pid-random` by default) names its pid; the only one when there is one.

    Raises LookupError when several run and none matches: killing the wrong worker would measure nothing."""
    for process in processes:
        if worker_id and f"-{process.pid}-" in worker_id:
            return process
    if len(processes) == 1:
        return processes[0]
    raise LookupError(f"no worker process matches the owner {worker_id!r}")


def lease_holder(redis_url: str, sid: str) -> str | None:
    """The worker holding the session's lease right now (None: no lease)."""
    import redis

    from protocol import keys

    client = redis.Redis.from_url(redis_url)
    try:
        raw = client.get(keys.lease(sid))
    finally:
        client.close()
    return raw.decode() if raw is not None else None


async def kill_owner(stack, http, sid: str, out: dict, restart: bool = True) -> None:
    """SIGKILL the worker owning the session (its lease holder, else the record's `worker`); with `restart`, start
    a new one at once (what `flashmono serve`'s supervisor does), else leave the standby workers to take over."""
    owner = await asyncio.to_thread(lease_holder, stack.redis_url, sid)
    if owner is None:
        owner = (await http.get(f"/v1/sessions/{sid}")).json().get("worker")
    victim = process_of(owner, stack.workers)
    out["at"] = time.monotonic()
    out["at_wall"] = time.time()
    out["owner"] = owner
    victim.send_signal(signal.SIGKILL)
    await asyncio.to_thread(victim.wait)
    stack.workers.remove(victim)
    out["restarted"] = restart
    if restart:
        stack.add_worker()


async def kill_when(progress: Callable[[], tuple[int, int]], sent: int, stack, http, sid: str, out: dict,
                    min_poses: int = 5, restart: bool = True) -> None:
    """Once `progress()` = (frames on the wire, poses received) reaches `sent` frames and `min_poses` poses, kill
    the owning worker (see kill_owner)."""
    while True:
        on_wire, posed = progress()
        if on_wire >= sent and posed >= min_poses:
            break
        await asyncio.sleep(0.02)
    out["at_frame_sent"] = on_wire
    out["poses_before"] = posed
    await kill_owner(stack, http, sid, out, restart=restart)


def takeover_phases(redis_url: str, sid: str, killed_at: float) -> dict[str, Any] | None:
    """Where the kill gap went, from the new owner's `takeover` timeline (wall times) in the session record:
    seconds from the kill to the job's claim (lease expiry noticed), to the runner's start (lease acquired), the
    restore, the replay of the frames after the snapshot, and the first pose stored."""
    import redis

    from protocol import keys

    client = redis.Redis.from_url(redis_url)
    try:
        raw = client.hget(keys.session(sid), "takeover")
    finally:
        client.close()
    if raw is None:
        return None
    t = json.loads(raw)
    marks = [("claimed", t.get("claimed_at")), ("started", t.get("started_at")), ("restored", t.get("restored_at")),
             ("replayed", t.get("replay_done_at")), ("first_pose", t.get("first_pose_at"))]
    phases: dict[str, Any] = {"worker": t.get("worker"), "snapshot_seq": t.get("snapshot_seq"),
                              "frames_replayed": t.get("replayed"), "first_pose_seq": t.get("first_pose_seq")}
    previous = killed_at
    for name, at in marks:
        phases[f"{name}_after_kill_s"] = None if at is None else round(at - killed_at, 3)
        phases[f"{name}_phase_s"] = None if at is None else round(at - previous, 3)
        previous = previous if at is None else at
    return phases
