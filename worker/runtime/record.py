"""A worker's writes to a session's record, each one atomic and only while the record exists.

A session deleted while its worker still runs must stay deleted: a plain HSET after the gateway's delete would
recreate a partial record (no id, no status) that every later request trips over. Every write here checks that
the record exists in the same Lua call, and reports False when it does not (the session is gone).
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime

import redis

from protocol import keys
from protocol.messages import ErrorMessage

_UPDATE = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
for i = 1, #ARGV, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
return 1
"""
# ARGV: n (the count of session field/value arguments), the session's fields and values, then seq/record pairs
_STORE_TRAJECTORY = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
local n = tonumber(ARGV[1])
for i = 2, n, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
for i = n + 2, #ARGV, 2 do redis.call('HSET', KEYS[2], ARGV[i], ARGV[i + 1]) end
return 1
"""
# The last step of a session (finished or failed): its fields, its final outbound message, the inbox entry acked;
# then what only served the live session (frames, messages, requests) expires after ARGV[4] s, and, with a
# retention (ARGV[5] > 0), everything else after that many seconds.
_CLOSE = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
for i = 6, #ARGV, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
redis.call('XADD', KEYS[2], 'MAXLEN', '~', ARGV[2], '*', 'msg', ARGV[1])
if ARGV[3] ~= '' then redis.call('XACK', KEYS[3], 'workers', ARGV[3]) end
for i = 2, 5 do redis.call('PEXPIRE', KEYS[i], math.floor(tonumber(ARGV[4]) * 1000)) end
if tonumber(ARGV[5]) > 0 then
  for i = 6, 9 do redis.call('PEXPIRE', KEYS[i], math.floor(tonumber(ARGV[5]) * 1000)) end
  redis.call('PEXPIRE', KEYS[1], math.floor(tonumber(ARGV[5]) * 1000))
end
return 1
"""

# Idle: abandon only a session that takes frames and has none waiting (a frame that just got in keeps it alive)
_ABANDON = """
local f = redis.call('HMGET', KEYS[1], 'status', 'frames_received', 'frames_processed', 'frames_rejected')
if not f[1] or (f[1] ~= 'created' and f[1] ~= 'streaming') then return 0 end
if tonumber(f[2] or '0') - tonumber(f[3] or '0') - tonumber(f[4] or '0') > 0 then return 0 end
redis.call('HSET', KEYS[1], 'status', 'abandoned', 'abandoned_at', ARGV[3], 'updated_at', ARGV[4])
redis.call('XADD', KEYS[2], 'MAXLEN', '~', ARGV[2], '*', 'msg', ARGV[1])
return 1
"""


def _flat(mapping: Mapping[str | int, object]) -> list:
    return [x for pair in mapping.items() for x in pair]


class SessionRecord:
    """Existence-checked writes to one session's hash (and the keys that go with it)."""

    def __init__(self, client: redis.Redis, session_id: str) -> None:
        self.session_id = session_id
        self._update = client.register_script(_UPDATE)
        self._store_trajectory = client.register_script(_STORE_TRAJECTORY)
        self._close = client.register_script(_CLOSE)
        self._abandon = client.register_script(_ABANDON)

    def update(self, fields: Mapping[str, object]) -> bool:
        """HSET `fields`; False when the session no longer exists."""
        return bool(self._update(keys=[keys.session(self.session_id)], args=_flat(fields)))

    def store_trajectory(self, poses: Mapping[int, bytes], fields: Mapping[str, object]) -> bool:
        """Every pose record (seq -> msgpack) and the session's `fields`, together; False when it is gone."""
        session_args = _flat(fields)
        return bool(self._store_trajectory(keys=[keys.session(self.session_id), keys.poses(self.session_id)],
                                           args=[len(session_args), *session_args, *_flat(poses)]))

    def close(self, fields: Mapping[str, object], message: bytes, outbox_maxlen: int,
              inbox_entry: bytes | None = None, transient_ttl_s: float = 3600.0, retention_s: float = 0.0) -> bool:
        """Set the final `fields` (status...), publish `message` and ack `inbox_entry`, together. The live-only
        keys (inbox, outbox, requests, in-flight mark) expire after `transient_ttl_s`; with `retention_s` > 0 the
        record, trajectory, snapshot (and its trajectory chunks) and rejections expire after it (0: kept)."""
        sid = self.session_id
        return bool(self._close(keys=[keys.session(sid), keys.outbox(sid), keys.inbox(sid), keys.session_requests(sid),
                                      keys.inflight(sid), keys.poses(sid), keys.snapshot(sid), keys.rejected(sid),
                                      keys.snapshot_chunks(sid)],
                                args=[message, outbox_maxlen, inbox_entry or b"", transient_ttl_s, retention_s,
                                      *_flat(fields)]))

    def abandon(self, message: bytes, outbox_maxlen: int, now_epoch_s: float, now_iso: str) -> bool:
        """Mark an idle session `abandoned` (publishing `message`) unless frames wait or it no longer takes any."""
        return bool(self._abandon(keys=[keys.session(self.session_id), keys.outbox(self.session_id)],
                                  args=[message, outbox_maxlen, f"{now_epoch_s:.3f}", now_iso]))


def abandon_unstarted(client: redis.Redis, session_id: str, idle_s: float, outbox_maxlen: int) -> bool:
    """Abandon a session that got no frame within `idle_s` of its creation (no worker ever ran it)."""
    message = ErrorMessage(code="abandoned",
                           message=f"no frame within {idle_s:g} s of its creation: the session was abandoned; "
                                   "open a stream within the grace period to resume it").to_json().encode()
    stamp = datetime.now(UTC)
    return SessionRecord(client, session_id).abandon(message, outbox_maxlen, stamp.timestamp(),
                                                     stamp.isoformat(timespec="milliseconds"))
