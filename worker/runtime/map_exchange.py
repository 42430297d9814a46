"""Places shared live between the sessions running in one map, through the map's `live` stream (protocol.keys).

Each `extend` session, once anchored in the map, offers its keyframes (their corners with a depth, in the map's
world: worker.maps.SessionInMap.share_keyframe); the runner publishes them and reads what the other sessions in
the map published, which its session then looks frames up among as well. Two devices mapping a room together so
find each other's new places: a keyframe of one found among the other's holds it to the other's estimate (a prior
in its pose graph), either way. A session reads the stream from its start: one restored elsewhere finds them all
again.
"""

from __future__ import annotations

import time
from typing import Any

import redis

from protocol import keys
from protocol.codec import pack, unpack

LIVE_MAXLEN = 2000  # places kept in a map's live stream (about 40 KB each)
EXCHANGE_EVERY_S = 0.5  # at most this often, besides every keyframe


class MapExchange:
    """One session's side of its map's live stream (see the module docstring)."""

    def __init__(self, client: redis.Redis, session_id: str, in_map: Any) -> None:
        self.client = client
        self.session_id = session_id
        self.in_map = in_map
        self.stream = keys.map_live(in_map.map_id)
        self.last_id = b"0-0"
        self._at = 0.0

    def exchange(self, keyframe: bool) -> int:
        """Publish this session's new places, take the others' (on a keyframe, else at most every
        EXCHANGE_EVERY_S); how many were taken."""
        now = time.monotonic()
        if not keyframe and now - self._at < EXCHANGE_EVERY_S:
            return 0
        self._at = now
        outgoing = self.in_map.take_outgoing()
        if outgoing:
            pipe = self.client.pipeline(transaction=False)
            for entry in outgoing:
                pipe.xadd(self.stream, {"e": pack({**entry, "session": self.session_id})}, maxlen=LIVE_MAXLEN,
                          approximate=True)
            pipe.execute()
        taken = []
        while True:
            read = self.client.xread({self.stream: self.last_id}, count=100)
            if not read:
                break
            for entry_id, fields in read[0][1]:
                self.last_id = entry_id
                entry = unpack(fields[b"e"])
                if entry.get("session") != self.session_id:
                    taken.append(entry)
        if taken:
            self.in_map.add_shared(taken)
        return len(taken)
