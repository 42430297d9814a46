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
from dataclasses import dataclass, field

import redis.asyncio as aioredis
from redis.crc import key_slot

from protocol import keys
from worker.runtime.connection import is_cluster
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
    """Start with `start()`, stop with `stop()`; `subscribe()` / `unsubscribe()` as streams open and close.

    On a single instance one reader task serves every subscribed session with one XREAD. A Redis Cluster refuses
    an XREAD over keys of several hash slots, and each session's outbox has its own slot (its id is the hash tag):
    there the hub runs one reader per slot in use, each on its own connection, so a gateway holds about one Redis
    connection per streaming session (bounded by FLASHMONO_MAX_STREAMS)."""

    def __init__(self, client: aioredis.Redis, block_ms: int = 200, count: int = 256,
                 deleted_check_s: float = 3.0) -> None:
        self.client = client
        self.block_ms = block_ms
        self.count = count
        self.deleted_check_s = deleted_check_s
        self._subs: dict[str, list[Subscription]] = {}
        self._groups: dict[int, set[str]] = {}  # reader group -> its subscribed session ids
        self._readers: dict[int, asyncio.Task] = {}
        self._checker: asyncio.Task | None = None
        self._cluster = is_cluster(client)

    @property
    def streams(self) -> int:
        return sum(len(subs) for subs in self._subs.values())

    def _group_of(self, session_id: str) -> int:
        return key_slot(keys.outbox(session_id).encode()) if self._cluster else 0

    def start(self) -> None:
        self._checker = asyncio.create_task(self._check_deleted_loop(), name="outbox-hub-deleted")

    async def stop(self) -> None:
        tasks = [t for t in (self._checker, *self._readers.values()) if t is not None]
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except asyncio.CancelledError:
                pass
        self._readers.clear()

    def subscribe(self, session_id: str, last_id: str) -> Subscription:
        """Entries of the session's outbox after `last_id`, in order."""
        sub = Subscription(session_id, last_id)
        self._subs.setdefault(session_id, []).append(sub)
        group = self._group_of(session_id)
        self._groups.setdefault(group, set()).add(session_id)
        if group not in self._readers:
            self._readers[group] = asyncio.create_task(self._read_group(group), name=f"outbox-hub-{group}")
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        subs = self._subs.get(sub.session_id, [])
        if sub in subs:
            subs.remove(sub)
        if not subs:
            self._forget(sub.session_id)

    def _forget(self, session_id: str) -> None:
        self._subs.pop(session_id, None)
        group = self._groups.get(self._group_of(session_id))
        if group is not None:
            group.discard(session_id)

    async def _read_group(self, group: int) -> None:
        """Read the outboxes of one group's sessions until none is subscribed (then the task ends)."""
        backoff = Backoff()
        outage = OutageLog(log, "outbox hub")
        while True:
            session_ids = self._groups.get(group)
            if not session_ids:  # no await between this check and the removal: subscribe() sees a consistent map
                self._groups.pop(group, None)
                del self._readers[group]
                return
            try:
                await self._read_once(session_ids)
                outage.recovered()
                backoff.reset()
            except (*REDIS_DOWN, RuntimeError) as err:  # RuntimeError: see outage.closed_transport
                outage.failed(err)
                await asyncio.sleep(backoff.next_delay())

    async def _read_once(self, session_ids: set[str]) -> None:
        # each session is read from the oldest position any of its subscribers still needs
        positions = {sid: min((s.last_id for s in self._subs[sid]), key=_id_tuple) for sid in session_ids
                     if self._subs.get(sid)}
        if not positions:
            return
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

    async def _check_deleted_loop(self) -> None:
        while True:
            await asyncio.sleep(self.deleted_check_s)
            if not self._subs:
                continue
            try:
                await self._drop_deleted()
            except REDIS_DOWN:
                pass  # the readers log the outage; checked again next time

    async def _drop_deleted(self) -> None:
        session_ids = list(self._subs)
        pipe = self.client.pipeline(transaction=False)
        for session_id in session_ids:
            pipe.exists(keys.session(session_id))
        for session_id, exists in zip(session_ids, await pipe.execute()):
            if not exists:
                for sub in self._subs.get(session_id, []):
                    sub.queue.put_nowait(SESSION_DELETED)
                self._forget(session_id)


def _id_tuple(stream_id: str) -> tuple[int, int]:
    ms, _, seq = stream_id.partition("-")
    return int(ms), int(seq or 0)
