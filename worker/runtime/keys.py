"""The Redis key layout shared by the gateway and the workers (one place, so both sides agree).

Per session `{id}`:
  fm:session:{id}        hash   the session record (see `SESSION_FIELDS`), counters, owner key hash, last seq
  fm:s:{id}:in           stream frames and control messages from the gateway (consumer group "workers")
  fm:s:{id}:out          stream results for the gateway to forward (pose, loop_closed, error, finished)
  fm:s:{id}:poses        hash   seq -> msgpack {timestamp, pose, kf}; the trajectory, idempotent by seq
  fm:s:{id}:rejected     hash   seq -> error code of frames the worker refused (idempotent by seq)
  fm:s:{id}:snap         hash   {data, seq, stream_id, keyframes}: the last engine snapshot
  fm:s:{id}:req          stream render/export requests for the live owner
  fm:s:{id}:inflight     string "<seq>:<attempts>" of the frame being processed (poison-frame quarantine)
  fm:lease:{id}          string worker id owning the session (expires unless renewed)
Global:
  fm:sessions            zset   members "<created_us>:<id>" (score 0, lexicographic order) for listing
  fm:jobs                stream one entry per session to run (consumer group "workers")
  fm:requests            stream render/export requests for finished sessions (any worker)
  fm:worker:{wid}        string heartbeat of a live worker (expires)
  fm:workerstats:{wid}   hash   per-stage latency sums and counts
  fm:reply:{request_id}  list   the reply to one request
  fm:owner:{key_id}:live zset   ids of the sessions an API key created that may still be live (per-key quota)
"""

from __future__ import annotations

GROUP = "workers"
SESSIONS_INDEX = "fm:sessions"
JOBS = "fm:jobs"
REQUESTS = "fm:requests"
WORKER_PREFIX = "fm:worker:"
WORKER_STATS_PREFIX = "fm:workerstats:"

STATUSES = ("created", "streaming", "finishing", "finished", "failed", "abandoned")
LIVE_STATUSES = ("created", "streaming", "finishing")


def session(session_id: str) -> str:
    return f"fm:session:{session_id}"


def inbox(session_id: str) -> str:
    return f"fm:s:{session_id}:in"


def outbox(session_id: str) -> str:
    return f"fm:s:{session_id}:out"


def poses(session_id: str) -> str:
    return f"fm:s:{session_id}:poses"


def rejected(session_id: str) -> str:
    return f"fm:s:{session_id}:rejected"


def snapshot(session_id: str) -> str:
    return f"fm:s:{session_id}:snap"


def session_requests(session_id: str) -> str:
    return f"fm:s:{session_id}:req"


def inflight(session_id: str) -> str:
    return f"fm:s:{session_id}:inflight"


def lease(session_id: str) -> str:
    return f"fm:lease:{session_id}"


def worker(worker_id: str) -> str:
    return f"{WORKER_PREFIX}{worker_id}"


def worker_stats(worker_id: str) -> str:
    return f"{WORKER_STATS_PREFIX}{worker_id}"


def owner_live(key_id: str) -> str:
    return f"fm:owner:{key_id}:live"


def reply(request_id: str) -> str:
    return f"fm:reply:{request_id}"


def all_session_keys(session_id: str) -> list[str]:
    """Every key that belongs to one session (deleted together)."""
    return [session(session_id), inbox(session_id), outbox(session_id), poses(session_id), rejected(session_id),
            snapshot(session_id), session_requests(session_id), lease(session_id), inflight(session_id)]
