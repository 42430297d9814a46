"""Progress while a session finishes: the engine's final refinement can take a minute, so the runner posts
`finishing` messages (protocol.messages.FinishingMessage: elapsed_s, phase, done, total, eta_s) to the session's
outbox when `finish` starts and every `every_s` seconds until it ends (the phase and its progress where the engine
reports them: `worker.pipeline.finish_status`). Clients see the server is working (and their idle timeouts
restart) and how long it will take, instead of a silent stream."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import redis

from protocol import keys
from protocol.messages import FinishingMessage

log = logging.getLogger(__name__)


class FinishProgress:
    """Context manager around `engine.finish()` that posts `finishing` messages from a background thread."""

    def __init__(self, client: redis.Redis, session_id: str, every_s: float = 2.0, outbox_maxlen: int = 5000,
                 status: Callable[[], dict[str, Any]] | None = None) -> None:
        if every_s <= 0:
            raise ValueError("every_s must be positive")
        self.client, self.session_id = client, session_id
        self.every_s, self.outbox_maxlen = every_s, outbox_maxlen
        self.status = status
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
        body: dict[str, Any] = {}
        if self.status is not None:
            try:
                body = {k: v for k, v in self.status().items() if k != "elapsed_s" and v is not None}
            except Exception:  # a progress report must never fail the finish
                log.exception("finish status of session %s unreadable", self.session_id)
        message = FinishingMessage(elapsed_s=round(time.monotonic() - self._start, 1), **body)
        try:
            self.client.xadd(keys.outbox(self.session_id), {"msg": message.to_json().encode()},
                             maxlen=self.outbox_maxlen, approximate=True)
        except redis.RedisError as err:  # progress is best effort: the finish itself must not fail for it
            log.warning("could not post finish progress of session %s: %s", self.session_id, err)
