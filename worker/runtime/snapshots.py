"""A session's engine snapshot in Redis: the bytes in `keys.snapshot` and, for a chunked snapshot, the manifest of
the trajectory chunks it needs (field `chunks`, JSON) with the chunks themselves in `keys.snapshot_chunks` (chunk ->
bytes, each written once, or again at a new version; see worker.engine.snapshot_chunks). A snapshot and the chunks
it adds are written in one Lua call fenced on the lease, so the chunks in Redis always match the newest snapshot.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import redis

from worker.engine.snapshot_chunks import ChunkWrite, chunk_versions
from worker.runtime import keys

# KEYS: snapshot, inbox, lease, session record, chunks; ARGV: worker, data, seq, stream id, engine, created_at,
# manifest ('' for a self-contained snapshot), then chunk/bytes pairs. Fenced on the lease and the record.
_STORE_SNAPSHOT = """
if redis.call('EXISTS', KEYS[4]) == 0 then return -1 end
if redis.call('GET', KEYS[3]) ~= ARGV[1] then return -2 end
redis.call('HSET', KEYS[1], 'data', ARGV[2], 'seq', ARGV[3], 'stream_id', ARGV[4], 'engine', ARGV[5],
           'created_at', ARGV[6])
if ARGV[7] == '' then redis.call('HDEL', KEYS[1], 'chunks') else redis.call('HSET', KEYS[1], 'chunks', ARGV[7]) end
for i = 8, #ARGV, 2 do redis.call('HSET', KEYS[5], ARGV[i], ARGV[i + 1]) end
redis.call('XTRIM', KEYS[2], 'MINID', ARGV[4])
return 1
"""


@dataclass
class StoredSnapshot:
    """A snapshot as read back: what `restore_engine` takes, and where the inbox replay starts."""

    engine: str
    data: bytes
    seq: int
    stream_id: bytes
    chunks: dict[int, bytes]  # the trajectory chunks of a chunked snapshot (empty for a self-contained one)
    versions: dict[int, int]  # chunk -> version of those chunks


def read_snapshot(client: redis.Redis, session_id: str) -> StoredSnapshot | None:
    """The session's newest snapshot with the chunks it needs, or None when it has none."""
    snap = client.hgetall(keys.snapshot(session_id))
    if not snap or b"data" not in snap:
        return None
    versions: dict[int, int] = {}
    chunks: dict[int, bytes] = {}
    if snap.get(b"chunks"):
        versions = chunk_versions(json.loads(snap[b"chunks"]))
        if versions:
            fields = [str(i) for i in versions]
            values = client.hmget(keys.snapshot_chunks(session_id), fields)
            chunks = {i: v for i, v in zip(versions, values) if v is not None}
    return StoredSnapshot(engine=snap[b"engine"].decode(), data=snap[b"data"], seq=int(snap[b"seq"]),
                          stream_id=snap[b"stream_id"], chunks=chunks, versions=versions)


class SnapshotWriter:
    """Writes one session's snapshots for one worker, remembering which trajectory chunks Redis holds."""

    def __init__(self, client: redis.Redis, session_id: str, worker_id: str) -> None:
        self.session_id = session_id
        self.worker_id = worker_id
        self.stored_chunks: dict[int, int] = {}  # chunk -> version in Redis (as of the newest snapshot)
        self.last_write_bytes = 0  # bytes the newest write sent (snapshot, manifest and new chunks)
        self._store = client.register_script(_STORE_SNAPSHOT)

    def restored(self, snapshot: StoredSnapshot) -> None:
        """The session continues from `snapshot`: the chunks it lists are in Redis."""
        self.stored_chunks = dict(snapshot.versions)

    def write(self, data: bytes, chunks: ChunkWrite | None, seq: int, entry_id: bytes, engine_kind: str,
              created_at: str) -> int:
        """Store a snapshot (and the chunks it adds); the Lua status: 1 stored, -1 session gone, -2 lease lost."""
        manifest = "" if chunks is None else json.dumps(chunks.manifest)
        pairs = [] if chunks is None else [x for i, raw in sorted(chunks.new.items()) for x in (str(i), raw)]
        status = self._store(keys=[keys.snapshot(self.session_id), keys.inbox(self.session_id),
                                   keys.lease(self.session_id), keys.session(self.session_id),
                                   keys.snapshot_chunks(self.session_id)],
                             args=[self.worker_id, data, seq, entry_id, engine_kind, created_at, manifest, *pairs])
        if status == 1 and chunks is not None:
            self.stored_chunks.update({i: chunks.versions()[i] for i in chunks.new})
        self.last_write_bytes = len(data) + len(manifest) + sum(len(v) for v in pairs[1::2])
        return int(status)
