"""Poison-frame quarantine: a frame on which workers keep dying (an out-of-memory kill, a crash in native code) is
not handed to worker after worker; once `max_attempts` workers started it without storing its result, the next
one fails the session with a clear error instead of processing it again.

One small key per session, `keys.inflight(id)` = "<seq>:<attempts>", is set before each frame is processed
(one round trip); it is overwritten by the next frame, so nothing grows.
"""

from __future__ import annotations

import redis

from protocol import keys

_BEGIN = """
if redis.call('EXISTS', KEYS[2]) == 0 then return 0 end
local value = redis.call('GET', KEYS[1])
local attempts = 1
if value then
  local seq, count = string.match(value, '^(%d+):(%d+)$')
  if seq == ARGV[1] then attempts = tonumber(count) + 1 end
end
redis.call('SET', KEYS[1], ARGV[1] .. ':' .. attempts)
return attempts
"""


class PoisonFrame(RuntimeError):
    """A frame that killed the workers that tried it; the session fails with this message."""


class FrameAttempts:
    """Counts, per session, the workers that started the current frame."""

    def __init__(self, client: redis.Redis, session_id: str, max_attempts: int) -> None:
        if max_attempts < 1:
            raise ValueError("max_attempts must be >= 1")
        self.key = keys.inflight(session_id)
        self.session_key = keys.session(session_id)
        self.max_attempts = max_attempts
        self._begin = client.register_script(_BEGIN)

    def begin(self, seq: int) -> int:
        """Record that this worker starts frame `seq` (its attempt number; 0 when the session no longer exists);
        PoisonFrame past max_attempts."""
        attempts = int(self._begin(keys=[self.key, self.session_key], args=[seq]))
        if attempts > self.max_attempts:
            died = attempts - 1
            raise PoisonFrame(f"frame {seq} was quarantined: the worker{'s' if died > 1 else ''} processing it "
                              f"died {died} time{'s' if died > 1 else ''} (out of memory or a crash); it is not "
                              "processed again and the session stops here")
        return attempts
