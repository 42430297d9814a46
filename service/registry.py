"""The gateway's view of Redis: the session registry, frame ingest, results, and requests to workers.

The key layout is `protocol.keys` (shared with the workers). All calls are async (redis.asyncio).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import msgpack
import redis.asyncio as aioredis
from redis.exceptions import NoScriptError

from protocol import keys
from protocol.lens import is_identity
from protocol.poses import similarity_scale
from service.paging import index_member, index_page
from worker.runtime.archive import BlobStore
from worker.runtime.connection import is_cluster
from worker.runtime.failpoints import failpoint
from worker.runtime.outage import closed_transport

# Atomically: check the session accepts frames, seq increases, the queue has room; enqueue; count.
# Returns {code, value, resend_from}: 0 accepted (value = queue depth), -1 no session, -2 not accepting (status),
# -3 seq not increasing (value = last seq; 5th item: the queue depth), -4 backpressure (value = queue depth),
# -5 frame size differs from the session's (the first accepted frame's; 4th item "WxH"): the engine takes one frame
# size per session. An accepted first frame (the session was `created`: 6th item 1) starts the session.
# Backpressure keeps the order: once frame N is refused for a full queue, every frame with a higher seq is refused
# too ("resend_from" = N) until a frame with seq <= N is accepted, so a pipelining sender can always re-send N.
_INGEST = """
local h = KEYS[1]
local fields = redis.call('HMGET', h, 'status', 'last_seq', 'frames_received', 'frames_processed',
                          'frames_rejected', 'resend_from', 'frame_size', 'frames_skipped')
if not fields[1] then return {-1, 0, -1} end
if fields[1] ~= 'created' and fields[1] ~= 'streaming' then return {-2, 0, -1} end
local seq = tonumber(ARGV[1])
local last = tonumber(fields[2] or '-1')
local depth = tonumber(fields[3] or '0') - tonumber(fields[4] or '0') - tonumber(fields[5] or '0')
              - tonumber(fields[8] or '0')
if seq <= last then return {-3, last, -1, '', depth} end
if fields[7] and ARGV[5] ~= '' and fields[7] ~= ARGV[5] then return {-5, 0, -1, fields[7]} end
local hold = tonumber(fields[6] or '-1')
if hold >= 0 and seq > hold then return {-4, depth, hold} end
if depth >= tonumber(ARGV[2]) then
  redis.call('HSET', h, 'resend_from', ARGV[1])
  return {-4, depth, seq}
end
redis.call('XADD', KEYS[2], '*', 'kind', 'frame', 'seq', ARGV[1], 'msg', ARGV[4])
local started = 0
if fields[1] == 'created' then
  redis.call('HSET', h, 'last_seq', ARGV[1], 'status', 'streaming', 'updated_at', ARGV[3])
  started = 1
else
  redis.call('HSET', h, 'last_seq', ARGV[1], 'updated_at', ARGV[3])
end
if hold >= 0 then redis.call('HDEL', h, 'resend_from') end
if not fields[7] and ARGV[5] ~= '' then redis.call('HSET', h, 'frame_size', ARGV[5]) end
redis.call('HINCRBY', h, 'frames_received', 1)
return {0, depth + 1, -1, '', -1, started}
"""
_FINISH = """
local status = redis.call('HGET', KEYS[1], 'status')
if not status then return -1 end
if status ~= 'created' and status ~= 'streaming' then return 0 end
redis.call('HSET', KEYS[1], 'status', 'finishing', 'updated_at', ARGV[1])
redis.call('XADD', KEYS[2], '*', 'kind', 'finish')
return 1
"""

_BLPOP_SLICE_S = 2.0
log = logging.getLogger(__name__)
# A stream opened on an abandoned session within the grace period revives it: streaming again (then a new job,
# see `revive`, so that a worker resumes it from its snapshot). 1 revived, 0 past the grace period, -1 not abandoned.
_REVIVE = """
local f = redis.call('HMGET', KEYS[1], 'status', 'abandoned_at')
if f[1] ~= 'abandoned' then return -1 end
if tonumber(ARGV[1]) - tonumber(f[2] or '0') > tonumber(ARGV[2]) then return 0 end
redis.call('HSET', KEYS[1], 'status', 'streaming', 'updated_at', ARGV[3])
redis.call('HDEL', KEYS[1], 'abandoned_at')
return 1
"""
INGEST_ACCEPTED, NO_SESSION, NOT_ACCEPTING, SEQ_NOT_INCREASING, QUEUE_FULL, SIZE_MISMATCH = 0, -1, -2, -3, -4, -5
_INT_FIELDS = ("frames_received", "frames_processed", "frames_rejected", "frames_skipped", "keyframes", "revision")
_FLOAT_FIELDS = ("mapping_lag_s", "frame_rate")
_OPTIONAL_INT_FIELDS = ("mapping_lag_keyframes", "tracking_side", "map_version")


def now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class IngestResult:
    code: int
    value: int
    resend_from: int = -1  # with QUEUE_FULL: the seq the sender must re-send next
    frame_size: str = ""  # with SIZE_MISMATCH: the session's frame size, "WxH"
    queue_depth: int = -1  # with SEQ_NOT_INCREASING: the session's queue depth
    started: bool = False  # accepted as the session's first frame: its status went from created to streaming


class ArchiveUnavailable(Exception):
    """An archived session's data is in a blob store this gateway cannot read."""


class RequestTimeout(Exception):
    """No worker answered a render/export request in time."""


class Registry:
    """Session records and streams in Redis, for one gateway process."""

    def __init__(self, client: aioredis.Redis, blobs: BlobStore | None = None, wait_replicas: int = 0,
                 wait_timeout_ms: int = 100) -> None:
        self.client = client
        self.blobs = blobs
        self.cluster = is_cluster(client)
        self.wait_replicas = wait_replicas
        self.wait_timeout_ms = wait_timeout_ms
        self.frames_unreplicated = 0  # acked although fewer than `wait_replicas` replicas confirmed them in time
        self._next_unreplicated_log = 0.0
        self._ingest = client.register_script(_INGEST)
        self._finish = client.register_script(_FINISH)
        self._revive = client.register_script(_REVIVE)

    # --- sessions -----------------------------------------------------------------------------------------------
    async def create_session(self, body: dict[str, Any], owner: str) -> dict[str, Any]:
        session_id = uuid.uuid4().hex
        created = now_iso()
        record = {
            "id": session_id, "name": body.get("name") or "", "device_id": body.get("device_id") or "",
            "status": "created", "created_at": created, "updated_at": created, "frames_received": 0,
            "frames_processed": 0, "frames_rejected": 0, "frames_skipped": 0, "keyframes": 0, "revision": 0,
            "worker": "", "preset": body.get("preset") or "", "pose_mode": body.get("pose_mode") or "",
            "skip_frames": int(bool(body.get("skip_frames"))), "tracking_side": body.get("tracking_side") or "",
            "frame_rate": body.get("frame_rate") or "",
            "intrinsics": json.dumps(body.get("intrinsics")), "depth_camera": json.dumps(body.get("depth_camera")),
            "metadata": json.dumps(body.get("metadata") or {}), "owner": owner, "last_seq": -1,
            "map_id": body.get("map_id") or "", "map_version": body.get("map_version") or "",
            "map_mode": body.get("map_mode") or "",
        }
        member = index_member(session_id)
        # atomic on a single instance; on a cluster these keys sit on several shards, so it is one round trip per
        # shard in this order: the record first, its job last (a record without a job is a session never started)
        pipe = self.client.pipeline(transaction=not self.cluster)
        pipe.hset(keys.session(session_id), mapping={**record, "index_member": member})
        pipe.zadd(keys.SESSIONS_INDEX, {member: 0})
        pipe.zadd(keys.owner_live(owner), {session_id: 0})
        pipe.xadd(keys.jobs(session_id), {"session_id": session_id})
        await pipe.execute()
        return parse_session(record)

    async def live_sessions_of(self, owner: str) -> int:
        """How many sessions `owner` created are still live (created, streaming, finishing); the others leave its
        set here. Concurrent creates may each see the same count: the quota can be passed by that many."""
        members = [m.decode() for m in await self.client.zrange(keys.owner_live(owner), 0, -1)]
        if not members:
            return 0
        pipe = self.client.pipeline(transaction=False)
        for session_id in members:
            pipe.hget(keys.session(session_id), "status")
        statuses = await pipe.execute()
        ended = [sid for sid, status in zip(members, statuses) if status is None
                 or status.decode() not in keys.LIVE_STATUSES]
        if ended:
            await self.client.zrem(keys.owner_live(owner), *ended)
        return len(members) - len(ended)

    async def get_raw(self, session_id: str) -> dict[str, str] | None:
        raw = await self.client.hgetall(keys.session(session_id))
        if not raw or b"id" not in raw or b"status" not in raw:
            return None  # absent, or a partial record left by an older worker writing after a delete
        return {k.decode(): v.decode() for k, v in raw.items()}

    async def list_sessions(self, *, status: str | None, device_id: str | None, name: str | None, limit: int,
                            cursor: str | None, owner: str | None) -> tuple[list[dict[str, Any]], str | None]:
        """Newest first. `cursor` is the index member of the last session of the previous page; next_cursor is
        None exactly when no further session matches."""
        records, next_cursor = await index_page(
            self.client, keys.SESSIONS_INDEX, keys.session,
            lambda record: _matches(record, status, device_id, name, owner), limit, cursor)
        return [parse_session(record) for record in records], next_cursor

    async def delete_session(self, session_id: str, record: dict[str, str]) -> None:
        failpoint("delete:gateway")
        pipe = self.client.pipeline(transaction=not self.cluster)
        pipe.execute_command("DEL", *keys.all_session_keys(session_id))  # one hash slot: one command on a cluster
        if record.get("index_member"):
            pipe.zrem(keys.SESSIONS_INDEX, record["index_member"])
        if record.get("owner"):
            pipe.zrem(keys.owner_live(record["owner"]), session_id)
        await pipe.execute()
        if record.get("archived") == "1" and self.blobs is not None:  # after: a crash leaves files, not a record
            await asyncio.to_thread(self.blobs.delete, session_id)

    # --- streaming ----------------------------------------------------------------------------------------------
    async def ingest_frame(self, session_id: str, seq: int, message: bytes, max_queue: int,
                           frame_size: str = "") -> IngestResult:
        """Queue one frame (see _INGEST); `frame_size` "WxH" must match the session's first frame. With
        `wait_replicas`, the frame is answered only once that many replicas hold it (or the wait timed out)."""
        script_keys = [keys.session(session_id), keys.inbox(session_id)]
        args = [seq, max_queue, now_iso(), message, frame_size]
        if self.wait_replicas:
            reply = await self._ingest_replicated(script_keys, args)
        else:
            try:
                reply = await self._ingest(keys=script_keys, args=args)
            except RuntimeError as err:  # the stream takes a RuntimeError for a client gone: not this one
                raise closed_transport(err) from err
        code, value, resend_from, *extra = reply
        return IngestResult(int(code), int(value), int(resend_from), extra[0].decode() if extra else "",
                            int(extra[1]) if len(extra) > 1 else -1, bool(int(extra[2])) if len(extra) > 2 else False)

    async def _ingest_replicated(self, script_keys: list[str], args: list) -> list:
        """The ingest script then WAIT on the same connection (WAIT covers that connection's writes): on a cluster
        both go to the primary of the session's slot. Redis replicates asynchronously: without this wait a
        primary that dies right after answering can take acked frames with it; with it, its replica has them."""
        reply, replicas = await self._evalsha_then_wait(script_keys, args)
        if isinstance(reply, NoScriptError):  # a new primary (after a failover) or a flushed script cache
            await self.client.script_load(_INGEST)
            reply, replicas = await self._evalsha_then_wait(script_keys, args)
        if isinstance(reply, Exception):
            raise reply
        if isinstance(replicas, Exception) or int(replicas) < self.wait_replicas:
            self.frames_unreplicated += 1
            if time.monotonic() >= self._next_unreplicated_log:  # a primary without its replica: once a minute
                log.warning("%d frames acked unconfirmed by %d replicas within %d ms so far (last: %s); is a "
                            "replica down?", self.frames_unreplicated, self.wait_replicas, self.wait_timeout_ms,
                            replicas)
                self._next_unreplicated_log = time.monotonic() + 60
        return reply

    async def _evalsha_then_wait(self, script_keys: list[str], args: list) -> list:
        pipe = self.client.pipeline(transaction=False)
        # (a cluster pipeline refuses pipe.evalsha; the raw command is routed by its keys like any other)
        pipe.execute_command("EVALSHA", self._ingest.sha, len(script_keys), *script_keys, *args)
        route = {"target_nodes": self.client.get_node_from_key(script_keys[0])} if self.cluster else {}
        pipe.execute_command("WAIT", self.wait_replicas, self.wait_timeout_ms, **route)
        try:
            return await pipe.execute(raise_on_error=False)
        except (RuntimeError, AttributeError) as err:
            # redis-py's asyncio cluster pipeline lets raw transport errors through on a connection the server
            # closed (uvloop's RuntimeError, or its writer already torn down): a Redis outage, not a bug here
            raise closed_transport(err) from err

    async def request_finish(self, session_id: str) -> int:
        """1 finishing now, 0 already finishing/finished, -1 no such session."""
        return int(await self._finish(keys=[keys.session(session_id), keys.inbox(session_id)], args=[now_iso()]))

    async def revive(self, session_id: str, grace_s: float) -> int:
        """1: the abandoned session streams again (a worker resumes it); 0: abandoned too long ago; -1: not
        abandoned. The job goes to its partition after the status changed (another shard on a cluster): a worker
        that reads it sees the session streaming."""
        revived = int(await self._revive(keys=[keys.session(session_id)],
                                         args=[f"{time.time():.3f}", grace_s, now_iso()]))
        if revived == 1:
            await self.queue_job(session_id)
        return revived

    async def queue_job(self, session_id: str) -> None:
        """A job for the session: a worker runs it now (a created session's first job waits, deferred, until a
        frame comes; the job queued when it came wakes a worker at once instead of at its next check)."""
        await self.client.xadd(keys.jobs(session_id), {"session_id": session_id})

    async def last_outbox_id(self, session_id: str) -> str:
        entries = await self.client.xrevrange(keys.outbox(session_id), count=1)
        return entries[0][0].decode() if entries else "0-0"

    # --- results ------------------------------------------------------------------------------------------------
    async def trajectory(self, session_id: str, which: str, archived: bool = False) -> list[dict[str, Any]]:
        """Poses by seq, from Redis, or from the blob store for an archived session."""
        if archived:
            if self.blobs is None:
                raise ArchiveUnavailable("this session was moved to the blob store; the gateway needs "
                                         "FLASHMONO_BLOB_DIR to serve its trajectory")
            raw = await asyncio.to_thread(self.blobs.poses, session_id)
        else:
            raw = await self.client.hgetall(keys.poses(session_id))
        poses = []
        for seq, blob in raw.items():
            record = msgpack.unpackb(blob, raw=False)
            if which == "keyframes" and not record.get("kf"):
                continue
            poses.append({"seq": int(seq), "timestamp": float(record["t"]), "pose": record["p"],
                          "scale": similarity_scale(record["p"])})
        poses.sort(key=lambda p: p["seq"])
        return poses

    async def request(self, session_id: str, kind: str, params: dict[str, Any], live: bool,
                      timeout_s: float) -> dict[str, Any]:
        """Ask the owning worker (live) or any worker (finished) to render/export; its reply dict."""
        request_id = uuid.uuid4().hex
        fields = {"id": request_id, "kind": kind, "params": json.dumps(params), "session_id": session_id}
        stream = keys.session_requests(session_id) if live else keys.requests(session_id)
        await self.client.xadd(stream, fields, maxlen=1000, approximate=True)
        # BLPOP in slices shorter than the client's socket timeout (5 s by default in redis-py), which would
        # otherwise end a longer wait early, whatever `timeout_s` says
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            reply = await self.client.blpop([keys.reply(request_id)], timeout=min(remaining, _BLPOP_SLICE_S))
            if reply is not None:
                return msgpack.unpackb(reply[1], raw=False)
        raise RequestTimeout(f"no worker answered within {timeout_s:g} s")

    # --- fleet --------------------------------------------------------------------------------------------------
    async def live_workers(self) -> list[str]:
        return [k.decode()[len(keys.WORKER_PREFIX):]
                async for k in self.client.scan_iter(match=f"{keys.WORKER_PREFIX}*", count=500)]

    async def worker_machines(self) -> list[dict[str, Any]]:
        """The machines of the live workers that publish one (SLAM workers), each as they publish it."""
        out = []
        async for key in self.client.scan_iter(match=f"{keys.WORKER_MACHINE_PREFIX}*", count=500):
            raw = await self.client.get(key)
            if raw:
                out.append(json.loads(raw))
        return out

    async def worker_stats(self) -> dict[str, dict[str, float]]:
        out = {}
        async for key in self.client.scan_iter(match=f"{keys.WORKER_STATS_PREFIX}*", count=500):
            raw = await self.client.hgetall(key)
            out[key.decode()[len(keys.WORKER_STATS_PREFIX):]] = {k.decode(): float(v) for k, v in raw.items()}
        return out

    async def lease_holder(self, session_id: str) -> str | None:
        value = await self.client.get(keys.lease(session_id))
        return value.decode() if value else None


def _matches(record: dict[str, str], status: str | None, device_id: str | None, name: str | None,
             owner: str | None) -> bool:
    return ((owner is None or record.get("owner") == owner) and (not status or record["status"] == status)
            and (device_id is None or record.get("device_id") == device_id)
            and (name is None or record.get("name") == name))


def engine_camera(record: dict[str, Any]) -> dict[str, Any] | None:
    """The pinhole camera the session's engine works with: as the worker published it, else the intrinsics given
    when they have no lens distortion (a distorted camera's pinhole is the worker's to compute); None while
    unknown."""
    if record.get("estimated_intrinsics"):
        return json.loads(record["estimated_intrinsics"])
    given = json.loads(record.get("intrinsics") or "null")
    return given if given is None or is_identity(given.get("distortion")) else None


def parse_session(record: dict[str, Any]) -> dict[str, Any]:
    """The API form of a session hash."""
    out: dict[str, Any] = {
        "id": record["id"], "name": record.get("name") or None, "device_id": record.get("device_id") or None,
        "status": record["status"], "created_at": record["created_at"], "updated_at": record["updated_at"],
        "worker": record.get("worker") or None, "preset": record.get("preset") or None,
        "pose_mode": record.get("pose_mode") or None, "intrinsics": json.loads(record.get("intrinsics") or "null"),
        "estimated_intrinsics": engine_camera(record),
        "metadata": json.loads(record.get("metadata") or "{}"), "error": record.get("error") or None,
        "depth_camera": json.loads(record.get("depth_camera") or "null"),
        "warnings": json.loads(record.get("warnings") or "[]"),
        "settings": json.loads(record.get("settings") or "null"),
    }
    if out["preset"] in (None, "auto") and out["settings"]:
        out["preset"] = out["settings"]["preset"]
    for name in _INT_FIELDS:
        out[name] = int(record.get(name) or 0)
    for name in _OPTIONAL_INT_FIELDS:
        out[name] = int(record[name]) if record.get(name) else None
    for name in _FLOAT_FIELDS:
        out[name] = float(record[name]) if record.get(name) else None
    out["tracking_state"] = record.get("tracking_state") or None
    out["map_id"], out["map_mode"] = record.get("map_id") or None, record.get("map_mode") or None
    out["skip_frames"] = record.get("skip_frames") == "1"
    out["last_seq"] = int(record.get("last_seq") or -1)
    return out
