"""The shape every pipeline stage shares: an input queue served by one thread, or inline in the caller.

A stage (mapping, loop closing) receives work items from the stage before it. `submit` never blocks the producer:
the queue is unbounded and each stage bounds its own backlog by shedding work (it sees its backlog through
`pending`). `at_marker(fn)` runs `fn` in the stage's thread once every item submitted before it is done: a
consistent cut of the pipeline without stopping the producer. `QueuedStage.snapshot_now` cuts a stage without
waiting for its queue: its state as of now, under its lock, with the items not done yet as data. A threaded stage
may have `idle` work: a small step run whenever its queue is empty (it returns False when there is nothing to do,
and the thread then waits for the next item). With `threaded=False` every item runs inline, in submission order,
and idle work never runs: deterministic runs for tests and offline evaluation.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

log = logging.getLogger(__name__)

_STOP = object()
# A stage's thread runs this much nicer than the process (Linux threads have their own nice value): tracking, in the
# caller's thread, gets a core first; mapping and loop closing take what is left (and their torch workers, created
# from them, inherit it).
BACKGROUND_NICE = 10


class _Marker:
    def __init__(self, action: Callable[[], None]) -> None:
        self.action = action


class StageThread:
    """One input queue and the thread that serves it with `handle(item)` (see the module docstring)."""

    def __init__(self, name: str, handle: Callable[[Any], None], threaded: bool,
                 idle: Callable[[], bool] | None = None) -> None:
        self.name = name
        self._handle = handle
        self._idle = idle
        self._error: BaseException | None = None
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._items = 0  # work items queued or running (markers not counted)
        self._count_lock = threading.Lock()
        self.on_failure: Callable[[BaseException], None] | None = None  # told, in the stage's thread, of a failure
        if threaded:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._run, name=name, daemon=True)
            self._thread.start()

    @property
    def threaded(self) -> bool:
        return self._queue is not None

    @property
    def pending(self) -> int:
        """Work items submitted and not finished yet (the running one included)."""
        return self._items

    def submit(self, item: Any) -> None:
        """Queue `item` (never blocks); handled at once when not threaded."""
        self.raise_if_failed()
        if self._queue is None:
            self._handle(item)
            return
        with self._count_lock:
            self._items += 1
        self._queue.put(item)

    def at_marker(self, action: Callable[[], None]) -> None:
        """Run `action` in the stage's thread after every item submitted so far (at once when not threaded)."""
        if self._queue is None:
            action()
        else:
            self._queue.put(_Marker(action))

    def wait_idle(self) -> None:
        """Block until everything submitted is done; re-raise a failure of the stage."""
        if self._queue is not None:
            self._queue.join()
        self.raise_if_failed()

    def close(self) -> None:
        """Stop the thread after the items already queued (idempotent)."""
        if self._queue is not None and self._thread is not None and self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join()
        self._queue = None

    def raise_if_failed(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the {self.name} stage failed: {self._error!r}") from self._error

    def _run(self) -> None:
        assert self._queue is not None
        _lower_priority(BACKGROUND_NICE)
        while True:
            item = self._next_item()
            try:
                if item is _STOP:
                    return
                if isinstance(item, _Marker):
                    item.action()
                elif self._error is None:
                    self._handle(item)
            except BaseException as err:  # noqa: BLE001 - reported to the producer on its next call
                log.exception("%s stage: a work item failed", self.name)
                self._failed(err)
            finally:
                if item is not _STOP and not isinstance(item, _Marker):
                    with self._count_lock:
                        self._items -= 1
                self._queue.task_done()

    def _next_item(self) -> Any:
        """The next queued item; while there is none, the idle work's steps (until it has nothing to do)."""
        assert self._queue is not None
        while self._idle is not None and self._error is None:
            try:
                return self._queue.get_nowait()
            except queue.Empty:
                pass
            try:
                if not self._idle():
                    break
            except BaseException as err:  # noqa: BLE001 - reported to the producer on its next call
                log.exception("%s stage: idle work failed", self.name)
                self._failed(err)
        return self._queue.get()

    def _failed(self, err: BaseException) -> None:
        self._error = err
        if self.on_failure is not None:
            self.on_failure(err)


class QueuedStage:
    """Base of the pipeline's stages: the queue-and-thread controls, delegated to `self._stage` (a StageThread the
    subclass makes with `self._handle_numbered` as its handler, after `_init_queue()`), and snapshots without waiting
    for the queue (`snapshot_now`). The subclass's `_process(item)` does the work; it calls `_done(item)` under
    `self.lock` at the moment the item's effect is in the stage's state, so that a snapshot taken under the lock has
    each item in one place: in the state, or among the items not done yet."""

    _stage: StageThread
    lock: threading.RLock
    name = "stage"

    def _init_queue(self) -> None:
        self.lock = threading.RLock()
        self._unfinished: deque[tuple[int, Any]] = deque()  # (submission number, item), in order
        self._submitted = 0
        self._unfinished_lock = threading.Lock()
        self._cuts: list[_Cut] = []  # snapshots asked for and not taken yet

    def submit(self, item: Any) -> None:
        """Queue a work item; never blocks (handled at once when not threaded)."""
        with self._unfinished_lock:
            self._submitted += 1
            self._unfinished.append((self._submitted, item))
            number = self._submitted
        self._stage.submit((number, item))

    def _handle_numbered(self, numbered: tuple[int, Any]) -> None:
        number, item = numbered
        # Every snapshot asked for is made before the next item starts, whether that item came before it (then it
        # goes into the snapshot as data) or after: a snapshot waits one work step at most, even where this thread
        # would win the lock from the snapshot's own thread item after item
        with self._unfinished_lock:
            due = list(self._cuts)
        for cut in due:
            with self.lock:
                cut.take()
        self._process(item)

    def _process(self, item: Any) -> None:
        raise NotImplementedError

    def _done(self, item: Any) -> None:
        """`item`'s effect is in the state (or it was dropped): it leaves the items not done (under `self.lock`)."""
        with self._unfinished_lock:
            for i, (_, waiting) in enumerate(self._unfinished):
                if waiting is item:
                    del self._unfinished[i]
                    return

    @contextlib.contextmanager
    def _reading(self) -> Iterator[None]:
        """The state's lock for a read from another thread."""
        with self.lock:
            yield

    def snapshot_now(self, deliver: Callable[[Callable[[], bytes]], None], pack_state: Callable[[list[Any]], bytes]
                     ) -> None:
        """The stage's state as of now, handed to `deliver(make_part)` without waiting for the queue: `make_part()`
        is `pack_state(items)`, called under the lock with the items submitted so far and not done yet (the one
        running included). A thread of its own makes it as soon as it gets the lock (one work step at most); the
        stage's thread makes it first if it is about to start another item."""
        with self._unfinished_lock:
            number = self._submitted

        def make() -> bytes:
            with self._unfinished_lock:
                items = [item for n, item in self._unfinished if n <= number]
            return pack_state(items)

        cut = _Cut(number, make, deliver)
        if not self._stage.threaded:
            cut.take()
            return
        with self._unfinished_lock:
            self._cuts.append(cut)

        def take() -> None:
            with self._reading():
                cut.take()
            with self._unfinished_lock:
                self._cuts.remove(cut)

        threading.Thread(target=take, name=f"{self.name}-snapshot", daemon=True).start()

    def at_marker(self, action: Callable[[], None]) -> None:
        """Run `action` in the stage's thread once every item submitted so far is done."""
        self._stage.at_marker(action)

    def wait_idle(self) -> None:
        """Block until every submitted item is done."""
        self._stage.wait_idle()

    def close(self) -> None:
        self._stage.close()

    def raise_if_failed(self) -> None:
        self._stage.raise_if_failed()

    def on_failure(self, callback: Callable[[BaseException], None]) -> None:
        """Call `callback(error)` in the stage's thread when a work item or idle step fails."""
        self._stage.on_failure = callback

    @property
    def pending(self) -> int:
        """Items submitted and not done yet."""
        return self._stage.pending


class _Cut:
    """A snapshot asked for after submission `number`: made once, by whichever thread comes first."""

    def __init__(self, number: int, make: Callable[[], bytes], deliver: Callable[[Callable[[], bytes]], None]) -> None:
        self.number = number
        self._make = make
        self._deliver = deliver
        self._taken = False
        self._lock = threading.Lock()

    def take(self) -> None:
        with self._lock:
            if self._taken:
                return
            self._taken = True
        self._deliver(self._make)


def _lower_priority(increment: int) -> None:
    """Make the calling thread `increment` nicer (best effort: where threads share one priority, nothing)."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + increment))
    except (AttributeError, OSError):
        pass
