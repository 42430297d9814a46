"""A session's engine snapshot in Redis: the bytes in `keys.snapshot` and, for an incremental snapshot, the
manifest of what it keeps outside (field `chunks`, JSON: trajectory chunks, array digests) with those parts in
`keys.snapshot_chunks` (field `<n>`: trajectory chunk n, each written once or again at a new version; field
`a:<digest>`: an array, written once; see worker.pipeline.snapshot_chunks). A snapshot, the parts it adds and the
removal of the arrays it no longer names happen in one Lua call fenced on the lease, so the parts in Redis always
match the newest snapshot; a self-contained snapshot (finish, abandon) drops them all.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import redis

from protocol import keys
from worker.pipeline.snapshot_chunks import ChunkWrite, chunk_versions

# KEYS: snapshot, inbox, lease, session record, parts; ARGV: worker, data, seq, stream id, engine, created_at,
# manifest ('' for a self-contained snapshot), n (count of field/bytes arguments), the fields and bytes to write,
# then the fields to remove. Fenced on the lease and the record.
_STORE_SNAPSHOT = """
if redis.call('EXISTS', KEYS[4]) == 0 then return -1 end
if redis.call('GET', KEYS[3]) ~= ARGV[1] then return -2 end
redis.call('HSET', KEYS[1], 'data', ARGV[2], 'seq', ARGV[3], 'stream_id', ARGV[4], 'engine', ARGV[5],
           'created_at', ARGV[6])
if ARGV[7] == '' then
  redis.call('HDEL', KEYS[1], 'chunks')
  redis.call('DEL', KEYS[5])
else
  redis.call('HSET', KEYS[1], 'chunks', ARGV[7])
end
local last = 8 + tonumber(ARGV[8])
for i = 9, last, 2 do redis.call('HSET', KEYS[5], ARGV[i], ARGV[i + 1]) end
for i = last + 1, #ARGV do redis.call('HDEL', KEYS[5], ARGV[i]) end
redis.call('XTRIM', KEYS[2], 'MINID', ARGV[4])
return 1
"""
ARRAY_FIELD = "a:"  # the field prefix of arrays kept outside a snapshot


@dataclass
class StoredSnapshot:
    """A snapshot as read back: what `restore_engine` takes, and where the inbox replay starts."""

    engine: str
    data: bytes
    seq: int
    stream_id: bytes
    chunks: dict[int | str, bytes]  # what an incremental snapshot keeps outside: trajectory chunks, arrays by digest
    versions: dict[int, int]  # chunk -> version of its trajectory chunks
    arrays: list[str]  # the digests of its arrays


def read_snapshot(client: redis.Redis, session_id: str) -> StoredSnapshot | None:
    """The session's newest snapshot with the chunks it needs, or None when it has none."""
    snap = client.hgetall(keys.snapshot(session_id))
    if not snap or b"data" not in snap:
        return None
    versions: dict[int, int] = {}
    arrays: list[str] = []
    chunks: dict[int | str, bytes] = {}
    if snap.get(b"chunks"):
        manifest = json.loads(snap[b"chunks"])
        versions, arrays = chunk_versions(manifest), list(manifest.get("arrays") or [])
        names: list[int | str] = [*versions, *arrays]
        if names:
            fields = [str(i) for i in versions] + [ARRAY_FIELD + d for d in arrays]
            values = client.hmget(keys.snapshot_chunks(session_id), fields)
            chunks = {name: value for name, value in zip(names, values) if value is not None}
    return StoredSnapshot(engine=snap[b"engine"].decode(), data=snap[b"data"], seq=int(snap[b"seq"]),
                          stream_id=snap[b"stream_id"], chunks=chunks, versions=versions, arrays=arrays)


class SnapshotWriter:
    """Writes one session's snapshots for one worker, remembering which trajectory chunks Redis holds."""

    def __init__(self, client: redis.Redis, session_id: str, worker_id: str) -> None:
        self.session_id = session_id
        self.worker_id = worker_id
        self.stored_chunks: dict[int, int] = {}  # trajectory chunk -> version in Redis (as of the newest snapshot)
        self.stored_arrays: set[str] = set()  # digests of the arrays in Redis
        self.last_write_bytes = 0  # bytes the newest write sent (snapshot, manifest, new chunks and arrays)
        self._store = client.register_script(_STORE_SNAPSHOT)

    def restored(self, snapshot: StoredSnapshot) -> None:
        """The session continues from `snapshot`: the parts it lists are in Redis."""
        self.stored_chunks = dict(snapshot.versions)
        self.stored_arrays = set(snapshot.arrays)

    def write(self, data: bytes, chunks: ChunkWrite | None, seq: int, entry_id: bytes, engine_kind: str,
              created_at: str) -> int:
        """Store a snapshot with the parts it adds (`chunks`: None for a self-contained one), dropping the arrays
        it no longer names; the Lua status: 1 stored, -1 session gone, -2 lease lost."""
        manifest, pairs, gone = "", [], []
        if chunks is not None:
            manifest = json.dumps({**chunks.manifest, "arrays": sorted(chunks.arrays)})
            pairs = [x for i, raw in sorted(chunks.new.items()) for x in (str(i), raw)]
            pairs += [x for d, raw in sorted(chunks.arrays.items()) if d not in self.stored_arrays
                      for x in (ARRAY_FIELD + d, raw)]
            gone = [ARRAY_FIELD + d for d in sorted(self.stored_arrays - set(chunks.arrays))]
        status = self._store(keys=[keys.snapshot(self.session_id), keys.inbox(self.session_id),
                                   keys.lease(self.session_id), keys.session(self.session_id),
                                   keys.snapshot_chunks(self.session_id)],
                             args=[self.worker_id, data, seq, entry_id, engine_kind, created_at, manifest,
                                   len(pairs), *pairs, *gone])
        if status == 1:
            if chunks is None:  # the parts are gone with it
                self.stored_chunks, self.stored_arrays = {}, set()
            else:
                versions = chunks.versions()
                self.stored_chunks.update({i: versions[i] for i in chunks.new})
                self.stored_arrays = set(chunks.arrays)
        self.last_write_bytes = len(data) + len(manifest) + sum(len(v) for v in pairs[1::2])
        return int(status)
