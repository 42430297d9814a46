"""Requests answered while a session finishes: the engine's final refinement holds the session's runner for up to
its budget (tens of seconds, more on a loaded machine), and a render or map export that waited for it could outlast
the gateway's request timeout (a 504 where the map exists). While `engine.finish()` runs, a background thread reads
the session's request stream and answers each request at once; the mapping stage lets it in between two refinement
steps (`MappingStage.refine_all`), so the answer is the map as refined so far."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import redis

from protocol import keys

log = logging.getLogger(__name__)


class RequestsWhileFinishing:
    """Context manager around `engine.finish()` that answers the session's requests from a background thread.

    handle(entry_id, fields) answers one request entry and acknowledges it (the runner's own handler)."""

    def __init__(self, client: redis.Redis, session_id: str, consumer: str,
                 handle: Callable[[bytes, dict[bytes, bytes]], None], block_ms: int = 200) -> None:
        if block_ms <= 0:
            raise ValueError("block_ms must be positive")
        self.client, self.session_id, self.consumer = client, session_id, consumer
        self.handle, self.block_ms = handle, block_ms
        self.answered = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"finish-requests-{session_id[:8]}", daemon=True)

    def __enter__(self) -> RequestsWhileFinishing:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=30)  # a request being answered ends first; the runner drains the rest after

    def _run(self) -> None:
        stream = keys.session_requests(self.session_id)
        while not self._stop.is_set():
            try:
                reply = self.client.xreadgroup(keys.GROUP, self.consumer, {stream: ">"}, count=10,
                                               block=self.block_ms)
            except redis.RedisError as err:  # best effort: the runner answers what is left after the finish
                log.warning("session %s: requests not read while finishing: %s", self.session_id, err)
                return
            for _stream, entries in reply or []:
                for entry_id, fields in entries:
                    self.handle(entry_id, fields)
                    self.answered += 1
