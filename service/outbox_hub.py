"""One reader of every open stream's outbox, per gateway process.

A blocking XREAD per WebSocket would hold one Redis connection per open stream (a thousand streams, a thousand
connections). The hub instead reads all subscribed outboxes with one XREAD on one connection and hands each entry
to its stream's queue; each stream forwards from its queue at its own pace. The reader survives Redis outages and
stalls of the process (a timed-out read is retried from the last id handed out: nothing is skipped or repeated),
and checks in one round trip every few seconds which subscribed sessions were deleted.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field

import redis.asyncio as aioredis

from worker.runtime import keys
from worker.runtime.outage import REDIS_DOWN, Backoff, OutageLog

log = logging.getLogger(__name__)
SESSION_DELETED = None  # what a subscription's queue yields when its session is gone


@dataclass(eq=False)
class Subscription:
    """One stream's view of its session's outbox: `queue` yields message texts (SESSION_DELETED at the end)."""

    session_id: str
    last_id: str
    queue: asyncio.Queue[str | None] = field(default_factory=asyncio.Queue)


class OutboxHub:
    """Start with `start()`, stop with `stop()`; `subscribe()` / `unsubscribe()` as streams open and close."""

    def __init__(self, client: aioredis.Redis, block_ms: int = 200, count: int = 256,
                 deleted_check_s: float = 3.0) -> None:
        self.client = client
        self.block_ms = block_ms
        self.count = count
        self.deleted_check_s = deleted_check_s
        self._subs: dict[str, list[Subscription]] = {}
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._next_check = 0.0

    @property
    def streams(self) -> int:
        return sum(len(subs) for subs in self._subs.values())

    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="outbox-hub")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass

    def subscribe(self, session_id: str, last_id: str) -> Subscription:
        """Entries of the session's outbox after `last_id`, in order."""
        sub = Subscription(session_id, last_id)
        self._subs.setdefault(session_id, []).append(sub)
        self._wake.set()
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        subs = self._subs.get(sub.session_id, [])
        if sub in subs:
            subs.remove(sub)
        if not subs:
            self._subs.pop(sub.session_id, None)

    async def _run(self) -> None:
        backoff = Backoff()
        outage = OutageLog(log, "outbox hub")
        while True:
            if not self._subs:
                self._wake.clear()
                await self._wake.wait()
                continue
            try:
                await self._read_once()
                if time.monotonic() >= self._next_check:
                    await self._drop_deleted()
                    self._next_check = time.monotonic() + self.deleted_check_s
                outage.recovered()
                backoff.reset()
            except REDIS_DOWN as err:
                outage.failed(err)
                await asyncio.sleep(backoff.next_delay())

    async def _read_once(self) -> None:
        # each session is read from the oldest position any of its subscribers still needs
        positions = {sid: min((s.last_id for s in subs), key=_id_tuple) for sid, subs in self._subs.items()}
        session_of = {keys.outbox(sid): sid for sid in positions}
        reply = await self.client.xread({keys.outbox(sid): pos for sid, pos in positions.items()},
                                        count=self.count, block=self.block_ms)
        for stream, entries in reply or []:
            for sub in self._subs.get(session_of[stream.decode()], []):
                for entry_id, fields in entries:
                    entry = entry_id.decode()
                    if _id_tuple(entry) > _id_tuple(sub.last_id):
                        sub.last_id = entry
                        sub.queue.put_nowait(fields[b"msg"].decode())

    async def _drop_deleted(self) -> None:
        session_ids = list(self._subs)
        pipe = self.client.pipeline(transaction=False)
        for session_id in session_ids:
            pipe.exists(keys.session(session_id))
        for session_id, exists in zip(session_ids, await pipe.execute()):
            if not exists:
                for sub in self._subs.pop(session_id, []):
                    sub.queue.put_nowait(SESSION_DELETED)


def _id_tuple(stream_id: str) -> tuple[int, int]:
    ms, _, seq = stream_id.partition("-")
    return int(ms), int(seq or 0)
