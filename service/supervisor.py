"""Keep N worker processes alive: a worker that exits (crash, OOM kill) is started again, with back-off when it
keeps dying right after its start. Used by `flashmono serve` and `LocalStack(supervise=True)`."""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from collections.abc import Callable

log = logging.getLogger("flashmono.supervisor")


class WorkerSupervisor:
    """Polls the workers every `poll_s`; a dead one is replaced by `spawn()` after a delay that doubles (from
    `first_delay_s` up to `max_delay_s`) while replacements die within `stable_s` of their start."""

    def __init__(self, spawn: Callable[[], subprocess.Popen], count: int, poll_s: float = 0.5,
                 first_delay_s: float = 0.5, max_delay_s: float = 30.0, stable_s: float = 30.0) -> None:
        self.spawn = spawn
        self.count = count
        self.poll_s = poll_s
        self.first_delay_s = first_delay_s
        self.max_delay_s = max_delay_s
        self.stable_s = stable_s
        self.workers: list[subprocess.Popen] = []
        self.restarts = 0
        self._started_at: list[float] = []
        self._delays: list[float] = []
        self._due: list[float | None] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def start(self) -> WorkerSupervisor:
        for _ in range(self.count):
            self.workers.append(self.spawn())
            self._started_at.append(time.monotonic())
            self._delays.append(self.first_delay_s)
            self._due.append(None)
        self._thread = threading.Thread(target=self._loop, name="worker-supervisor", daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            with self._lock:
                for i in range(len(self.workers)):
                    self._check(i)

    def _check(self, i: int) -> None:
        process, now = self.workers[i], time.monotonic()
        if process.poll() is None:
            if now - self._started_at[i] > self.stable_s:
                self._delays[i] = self.first_delay_s  # it has run long enough: the next crash restarts quickly
            return
        if self._due[i] is None:
            self._due[i] = now + self._delays[i]
            log.warning("worker pid %d exited with code %s; restarting it in %.1f s", process.pid,
                        process.returncode, self._delays[i])
            return
        if now < self._due[i] or self._stop.is_set():
            return
        self.workers[i] = self.spawn()
        self.restarts += 1
        self._started_at[i], self._due[i] = now, None
        self._delays[i] = min(self.max_delay_s, self._delays[i] * 2)
        log.warning("worker restarted as pid %d", self.workers[i].pid)

    def stop(self, timeout_s: float = 20.0) -> None:
        """Stop supervising, then SIGTERM every worker and wait (SIGKILL after `timeout_s`)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        with self._lock:
            for process in self.workers:
                if process.poll() is None:
                    process.terminate()
            for process in self.workers:
                try:
                    process.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
