"""The blob store of finished sessions: a directory (FLASHMONO_BLOB_DIR) that takes a finished session's bulky data
out of Redis after FLASHMONO_ARCHIVE_AFTER_S, with its map and trajectory still served from there.

Per session `<dir>/<id>/`: `snapshot.msgpack` ({engine, stream_id, seq, data}: the engine, for renders and the
map) and `poses.msgpack` ({seq: pose record}, the trajectory as Redis held it). Files are written to a temporary
name and renamed, so a reader never sees half a file; Redis keeps the small session record, marked `archived`.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from datetime import datetime
from pathlib import Path

import redis

from protocol import keys
from protocol.codec import pack, unpack

log = logging.getLogger(__name__)

# Only a finished, not yet archived session loses its Redis copies (and only once the files are in place).
_DROP_ARCHIVED = """
if redis.call('HGET', KEYS[1], 'status') ~= 'finished' then return 0 end
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4], KEYS[5])
redis.call('HSET', KEYS[1], 'archived', '1')
return 1
"""


class BlobStore:
    """Finished sessions' snapshots and trajectories as files under `root`."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def _dir(self, session_id: str) -> Path:
        if not session_id.isalnum():
            raise ValueError(f"bad session id {session_id!r}")
        return self.root / session_id

    def put(self, session_id: str, snapshot: dict[str, bytes], poses: dict[bytes, bytes]) -> None:
        directory = self._dir(session_id)
        directory.mkdir(parents=True, exist_ok=True)
        for name, value in (("snapshot.msgpack", snapshot), ("poses.msgpack", poses)):
            tmp = directory / f".{name}.{os.getpid()}.tmp"
            tmp.write_bytes(pack(value))
            tmp.replace(directory / name)

    def snapshot(self, session_id: str) -> dict[bytes, bytes] | None:
        """The snapshot hash as Redis held it ({b"engine", b"stream_id", b"seq", b"data"}), or None."""
        path = self._dir(session_id) / "snapshot.msgpack"
        return unpack(path.read_bytes()) if path.is_file() else None

    def delete(self, session_id: str) -> None:
        shutil.rmtree(self._dir(session_id), ignore_errors=True)

    def poses(self, session_id: str) -> dict[bytes, bytes]:
        path = self._dir(session_id) / "poses.msgpack"
        return unpack(path.read_bytes()) if path.is_file() else {}


def archive_finished(client: redis.Redis, store: BlobStore, after_s: float, limit: int = 200) -> int:
    """Move the finished sessions last updated more than `after_s` ago to `store`; how many moved."""
    drop = client.register_script(_DROP_ARCHIVED)
    members = [m.decode() for m in client.zrange(keys.SESSIONS_INDEX, 0, -1)]
    pipe = client.pipeline(transaction=False)
    for member in members:
        pipe.hmget(keys.session(member.split(":", 1)[1]), ["status", "updated_at", "archived"])
    moved = 0
    now = time.time()
    for member, (status, updated, archived) in zip(members, pipe.execute() if members else []):
        if moved >= limit or status != b"finished" or archived or updated is None:
            continue
        if now - datetime.fromisoformat(updated.decode()).timestamp() < after_s:
            continue
        session_id = member.split(":", 1)[1]
        if not client.set(keys.archiving(session_id), "1", nx=True, px=60_000):
            continue  # another worker is on it
        snapshot = client.hgetall(keys.snapshot(session_id))
        if not snapshot:
            continue
        store.put(session_id, snapshot, client.hgetall(keys.poses(session_id)))
        moved += drop(keys=[keys.session(session_id), keys.snapshot(session_id), keys.poses(session_id),
                            keys.rejected(session_id), keys.snapshot_chunks(session_id)])
        log.info("session %s archived to %s", session_id, store.root)
    return moved
