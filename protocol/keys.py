"""The Redis key layout shared by the gateway and the workers (one place, so both sides agree).

Every key of one session carries the session id as a Redis Cluster hash tag (`{id}`), so a session's keys live
in one hash slot, on one shard, and the Lua scripts and multi-key reads over them stay legal on a cluster; a
single instance ignores the braces. Per session `{id}`:
  fm:{id}:session        hash   the session record (see `SESSION_FIELDS`), counters, owner key hash, last seq
  fm:{id}:in             stream frames and control messages from the gateway (consumer group "workers")
  fm:{id}:out            stream results for the gateway to forward (pose, loop_closed, error, finished)
  fm:{id}:poses          hash   seq -> msgpack {timestamp, pose, kf}; the trajectory, idempotent by seq
  fm:{id}:rejected       hash   seq -> error code of frames the worker refused (idempotent by seq)
  fm:{id}:snap           hash   {data, seq, stream_id, engine, chunks}: the last engine snapshot
  fm:{id}:snapchunks     hash   chunk -> msgpack: the trajectory chunks a chunked snapshot lists (runtime.snapshots)
  fm:{id}:req            stream render/export requests for the live owner
  fm:{id}:inflight       string "<seq>:<attempts>" of the frame being processed (poison-frame quarantine)
  fm:{id}:lease          string worker id owning the session (expires unless renewed)
  fm:{id}:archiving      string a worker moving the finished session to the blob store (expires)
Per map `{map.<id>}` (a map's keys share one hash tag too, `map.` keeping it apart from the session ids; the
scripts that write them are protocol.map_store's):
  fm:{map.<id>}:map       hash   the map record: id, name, owner (the creator's key hash, as a session's), status,
                                 created_at, updated_at, latest (version), versions (the last allocated),
                                 index_member; per version v: v<v>.meta (the package's metadata, JSON), v<v>.size
                                 (bytes), v<v>.created_at, v<v>.session_id (the session that made it, or "")
  fm:{map.<id>}:packages  hash   version -> the package bytes (protocol.map_package); every version kept until the
                                 map is deleted
  fm:{map.<id>}:sessions  hash   session id -> JSON {role: built|used, map_mode, at}: the sessions that built the map
                                 and those created in it
  fm:{map.<id>}:live      stream the places (keyframes found in the map's world) the sessions running in the map add
                                 while they run, msgpack {session, keyframe, pose, places}; each of them reads the
                                 others' (worker.runtime.map_exchange)
Global: the work queues are split into `PARTITIONS` streams, each its own hash tag, so that on a cluster they
spread over the shards; a session's job and requests always go to the partition of its id, and workers read the
partitions in turn:
  fm:{jobs.P}            stream one entry per session to run (consumer group "workers"), P = 0..PARTITIONS-1
  fm:{requests.P}        stream render/export requests for finished sessions (any worker)
  fm:sessions            zset   members "<created_us>:<id>" (score 0, lexicographic order) for listing
  fm:maps                zset   members "<created_us>:<map id>" (the same) for listing maps
  fm:worker:{wid}        string heartbeat of a live worker (expires)
  fm:workerstats:{wid}   hash   per-stage latency sums and counts
  fm:workermachine:{wid} string JSON: the worker's machine (cores, CUDA, trained weights) for GET /v1/presets
  fm:reply:{request_id}  list   the reply to one request
  fm:owner:{key_id}:live zset   ids of the sessions an API key created that may still be live (per-key quota)
(`{wid}` etc. above are placeholders, not hash tags: those keys are single-key and hash as a whole.)

The layout before hash tags (`fm:session:<id>`, `fm:s:<id>:in`, `fm:lease:<id>`, `fm:jobs`, `fm:requests`) is
`LEGACY_*` here; `python -m worker.runtime.migrate` moves a single instance's data from it (see that module).
"""

from __future__ import annotations

import zlib
from typing import Literal, get_args

GROUP = "workers"
SESSIONS_INDEX = "fm:sessions"
MAPS_INDEX = "fm:maps"
PARTITIONS = 8
WORKER_PREFIX = "fm:worker:"
WORKER_STATS_PREFIX = "fm:workerstats:"
WORKER_MACHINE_PREFIX = "fm:workermachine:"
# the stages whose latency sums and counts a worker keeps in its fm:workerstats hash ("<stage>_sum", "<stage>_n")
WORKER_STAGES = ("read", "decode", "engine", "store", "dispatch", "dispatch_cpu", "snapshot", "render")

SessionStatus = Literal["created", "streaming", "finishing", "finished", "failed", "abandoned"]
STATUSES: tuple[str, ...] = get_args(SessionStatus)
LIVE_STATUSES = ("created", "streaming", "finishing")


def _tagged(session_id: str, part: str) -> str:
    return f"fm:{{{session_id}}}:{part}"


def session(session_id: str) -> str:
    return _tagged(session_id, "session")


def inbox(session_id: str) -> str:
    return _tagged(session_id, "in")


def outbox(session_id: str) -> str:
    return _tagged(session_id, "out")


def poses(session_id: str) -> str:
    return _tagged(session_id, "poses")


def rejected(session_id: str) -> str:
    return _tagged(session_id, "rejected")


def snapshot(session_id: str) -> str:
    return _tagged(session_id, "snap")


def snapshot_chunks(session_id: str) -> str:
    return _tagged(session_id, "snapchunks")


def session_requests(session_id: str) -> str:
    return _tagged(session_id, "req")


def inflight(session_id: str) -> str:
    return _tagged(session_id, "inflight")


def lease(session_id: str) -> str:
    return _tagged(session_id, "lease")


def archiving(session_id: str) -> str:
    return _tagged(session_id, "archiving")


def partition(session_id: str) -> int:
    """The work-queue partition of a session (stable across processes and versions)."""
    return zlib.crc32(session_id.encode()) % PARTITIONS


def jobs_partition(index: int) -> str:
    return f"fm:{{jobs.{index}}}"


def requests_partition(index: int) -> str:
    return f"fm:{{requests.{index}}}"


def jobs(session_id: str) -> str:
    """The jobs stream a session's job goes to."""
    return jobs_partition(partition(session_id))


def requests(session_id: str) -> str:
    """The stream requests for a finished session go to."""
    return requests_partition(partition(session_id))


JOB_STREAMS = tuple(jobs_partition(i) for i in range(PARTITIONS))
REQUEST_STREAMS = tuple(requests_partition(i) for i in range(PARTITIONS))


def worker(worker_id: str) -> str:
    return f"{WORKER_PREFIX}{worker_id}"


def worker_stats(worker_id: str) -> str:
    return f"{WORKER_STATS_PREFIX}{worker_id}"


def worker_machine(worker_id: str) -> str:
    return f"{WORKER_MACHINE_PREFIX}{worker_id}"


def owner_live(key_id: str) -> str:
    return f"fm:owner:{key_id}:live"


def reply(request_id: str) -> str:
    return f"fm:reply:{request_id}"


def all_session_keys(session_id: str) -> list[str]:
    """Every key that belongs to one session (deleted together; one hash slot)."""
    return [session(session_id), inbox(session_id), outbox(session_id), poses(session_id), rejected(session_id),
            snapshot(session_id), snapshot_chunks(session_id), session_requests(session_id), lease(session_id),
            inflight(session_id), archiving(session_id)]


def _map_tagged(map_id: str, part: str) -> str:
    return f"fm:{{map.{map_id}}}:{part}"


def map_record(map_id: str) -> str:
    return _map_tagged(map_id, "map")


def map_packages(map_id: str) -> str:
    return _map_tagged(map_id, "packages")


def map_sessions(map_id: str) -> str:
    return _map_tagged(map_id, "sessions")


def map_live(map_id: str) -> str:
    return _map_tagged(map_id, "live")


def all_map_keys(map_id: str) -> list[str]:
    """Every key of one map, every version included (deleted together; one hash slot)."""
    return [map_record(map_id), map_packages(map_id), map_sessions(map_id), map_live(map_id)]


# --- the layout before hash tags (read by worker.runtime.migrate only) -----------------------------------------
LEGACY_JOBS = "fm:jobs"
LEGACY_REQUESTS = "fm:requests"
LEGACY_SESSION_PREFIX = "fm:session:"


def legacy_session_keys(session_id: str) -> dict[str, str]:
    """{old name: new name} of every per-session key of the layout before hash tags."""
    old = {"session": f"fm:session:{session_id}", "in": f"fm:s:{session_id}:in", "out": f"fm:s:{session_id}:out",
           "poses": f"fm:s:{session_id}:poses", "rejected": f"fm:s:{session_id}:rejected",
           "snap": f"fm:s:{session_id}:snap", "req": f"fm:s:{session_id}:req",
           "inflight": f"fm:s:{session_id}:inflight", "lease": f"fm:lease:{session_id}",
           "archiving": f"fm:archiving:{session_id}"}
    return {name: _tagged(session_id, part) for part, name in old.items()}
