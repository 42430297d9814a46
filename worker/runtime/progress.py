"""Progress while a session finishes: the engine's final refinement can take a minute, so the runner posts
{"type": "finishing", "elapsed_s": ...} to the session's outbox when `finish` starts and every `every_s` seconds
until it ends. Clients see the server is working (and their idle timeouts restart) instead of a silent stream."""

from __future__ import annotations

import json
import logging
import threading
import time

import redis

from worker.runtime import keys

log = logging.getLogger(__name__)


class FinishProgress:
    """Context manager around `engine.finish()` that posts `finishing` messages from a background thread."""

    def __init__(self, client: redis.Redis, session_id: str, every_s: float = 2.0, outbox_maxlen: int = 5000) -> None:
        if every_s <= 0:
            raise ValueError("every_s must be positive")
        self.client, self.session_id = client, session_id
        self.every_s, self.outbox_maxlen = every_s, outbox_maxlen
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"finish-progress-{session_id[:8]}", daemon=True)
        self._start = 0.0

    def __enter__(self) -> FinishProgress:
        self._start = time.monotonic()
        self._post()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self._post()

    def _post(self) -> None:
        message = json.dumps({"type": "finishing", "elapsed_s": round(time.monotonic() - self._start, 1)})
        try:
            self.client.xadd(keys.outbox(self.session_id), {"msg": message.encode()}, maxlen=self.outbox_maxlen,
                             approximate=True)
        except redis.RedisError as err:  # progress is best effort: the finish itself must not fail for it
            log.warning("could not post finish progress of session %s: %s", self.session_id, err)
