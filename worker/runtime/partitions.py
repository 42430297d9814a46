"""Reading a work queue split into partition streams (`keys.JOB_STREAMS`, `keys.REQUEST_STREAMS`).

On a single instance one blocking XREADGROUP covers every partition, as one stream did. On a Redis Cluster each
partition may live on another shard and one XREADGROUP may only name streams of one hash slot, so a worker reads
the partitions in turn, blocking on each for a slice of `cycle_ms`: an entry waits at most about one cycle for an
idle worker (workers start their turns at different partitions).
"""

from __future__ import annotations

import redis

from protocol import keys
from worker.runtime.connection import is_cluster


class PartitionReader:
    """One consumer's reads of `streams` in the "workers" group."""

    def __init__(self, streams: tuple[str, ...], cycle_ms: int = 500, start: int = 0) -> None:
        if not streams or cycle_ms < 1:
            raise ValueError("need at least one stream and a positive cycle")
        self.streams = streams
        self.cycle_ms = cycle_ms
        self._turn = start % len(streams)

    def read(self, client: redis.Redis, consumer: str, count: int = 1, within_ms: int | None = None
             ) -> list[tuple[str, bytes, dict]]:
        """[(stream, entry id, fields)] new to the group: from every partition on a single instance (at most
        `count` each), from the partition whose turn it is on a cluster; often empty. `within_ms` shortens the
        wait (the caller has something due sooner than a cycle)."""
        cycle_ms = self.cycle_ms if within_ms is None else max(1, min(self.cycle_ms, within_ms))
        if is_cluster(client):
            stream = self.streams[self._turn]
            self._turn = (self._turn + 1) % len(self.streams)
            wanted = {stream: ">"}
            block_ms = max(1, cycle_ms // len(self.streams))
        else:
            wanted = dict.fromkeys(self.streams, ">")
            block_ms = cycle_ms
        reply = client.xreadgroup(keys.GROUP, consumer, wanted, count=count, block=block_ms)
        return [(_text(name), entry_id, fields) for name, entries in reply or [] for entry_id, fields in entries]


def _text(name: bytes | str) -> str:
    return name.decode() if isinstance(name, bytes) else name
