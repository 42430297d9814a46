"""Session ownership: one worker holds a session's lease (a Redis key with a TTL) and renews it by heartbeats.

A worker that dies stops renewing; the key expires and another worker may take the session over.
"""

from __future__ import annotations

import redis

from protocol import keys

_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('PEXPIRE', KEYS[1], ARGV[2])
end
return 0
"""
_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('DEL', KEYS[1])
end
return 0
"""


class Leases:
    """Acquire, renew and release session leases on behalf of one worker."""

    def __init__(self, client: redis.Redis, worker_id: str, ttl_ms: int) -> None:
        if ttl_ms < 100:
            raise ValueError("lease TTL must be at least 100 ms")
        self.client = client
        self.worker_id = worker_id
        self.ttl_ms = ttl_ms
        self._renew = client.register_script(_RENEW)
        self._release = client.register_script(_RELEASE)

    def acquire(self, session_id: str) -> bool:
        """Take the lease if nobody holds it (or we already do)."""
        if self.client.set(keys.lease(session_id), self.worker_id, nx=True, px=self.ttl_ms):
            return True
        return self.renew(session_id)

    def renew(self, session_id: str) -> bool:
        """Extend our lease; False when it expired or another worker holds it now."""
        return bool(self._renew(keys=[keys.lease(session_id)], args=[self.worker_id, self.ttl_ms]))

    def release(self, session_id: str) -> None:
        self._release(keys=[keys.lease(session_id)], args=[self.worker_id])


def lease_holder(client: redis.Redis, session_id: str) -> str | None:
    """The worker id holding the session's lease, or None."""
    value = client.get(keys.lease(session_id))
    return value.decode() if isinstance(value, bytes) else value
