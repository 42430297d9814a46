"""Reading a work queue split into partition streams (`keys.JOB_STREAMS`, `keys.REQUEST_STREAMS`).

On a Redis Cluster each partition may live on another shard, and one XREADGROUP may only name streams of one
hash slot; so a worker reads the partitions in turn, blocking on each for a slice of `cycle_ms`. An entry waits at
most about one cycle for an idle worker (several workers read at different points of the cycle).
"""

from __future__ import annotations

import redis

from worker.runtime import keys


class PartitionReader:
    """One consumer's turn-by-turn reads of `streams` in the "workers" group."""

    def __init__(self, streams: tuple[str, ...], cycle_ms: int = 500, start: int = 0) -> None:
        if not streams or cycle_ms < 1:
            raise ValueError("need at least one stream and a positive cycle")
        self.streams = streams
        self.block_ms = max(1, cycle_ms // len(streams))
        self._turn = start % len(streams)

    def read(self, client: redis.Redis, consumer: str, count: int = 1) -> list[tuple[str, bytes, dict]]:
        """[(stream, entry id, fields)] new to the group from the partition whose turn it is (often empty)."""
        stream = self.streams[self._turn]
        self._turn = (self._turn + 1) % len(self.streams)
        reply = client.xreadgroup(keys.GROUP, consumer, {stream: ">"}, count=count, block=self.block_ms)
        return [(stream, entry_id, fields) for _name, entries in reply or [] for entry_id, fields in entries]
