"""A snapshot assembled from parts that the pipeline's stages deliver from their own threads.

The tracking thread packs its part at once and asks each stage for its part at a marker in the stage's queue
(`StageThread.at_marker`), so no stage stops for it; the snapshot is complete when every part has arrived.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any


class SnapshotFuture:
    """Parts by name; `result()` waits for all of them and packs them with `assemble(parts) -> bytes`."""

    def __init__(self, names: list[str], assemble: Callable[[dict[str, Any]], bytes]) -> None:
        self._missing = set(names)
        self._parts: dict[str, Any] = {}
        self._error: BaseException | None = None
        self._assemble = assemble
        self._done = threading.Event()
        self._lock = threading.Lock()
        self.chunks: Any = None  # what a chunked snapshot keeps outside its bytes (a ChunkWrite)
        if not self._missing:
            self._done.set()

    def deliver(self, name: str, make_part: Callable[[], Any]) -> None:
        """Make part `name` (in the calling stage's thread) and store it, or the error making it raised."""
        try:
            part = make_part()
        except BaseException as err:  # noqa: BLE001 - the snapshot fails, the stage goes on
            with self._lock:
                self._error = err
            self._done.set()
            return
        with self._lock:
            self._parts[name] = part
            self._missing.discard(name)
            if not self._missing:
                self._done.set()

    def done(self) -> bool:
        """Whether every part has arrived (or one failed)."""
        return self._done.is_set()

    def result(self, timeout: float | None = None) -> bytes:
        """The snapshot's bytes, waiting up to `timeout` seconds for the parts; raises the error of a failed part,
        TimeoutError when the parts are not there in time."""
        if not self._done.wait(timeout):
            raise TimeoutError("the pipeline's stages have not delivered their snapshot parts yet")
        if self._error is not None:
            raise RuntimeError(f"a snapshot part failed: {self._error!r}") from self._error
        return self._assemble(dict(self._parts))
