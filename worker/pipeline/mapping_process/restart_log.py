"""What a replacement mapping process starts from: the last checkpoint of the map and the jobs submitted after it.

A checkpoint is a cut of the process's stage (the session's own snapshots, or one the proxy asks for). Its large
arrays are held here by digest and sent to the process once: a cut asked for is told which it need not send again,
and those stay held (pinned) until its reply comes.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from worker.pipeline.map_jobs import KeyframeJob, PoseUpdateJob

Job = KeyframeJob | PoseUpdateJob


@dataclass
class Checkpoint:
    """A cut of the stage: its packed state, how many jobs it covers, the arrays it refers to (by digest)."""

    data: bytes | None = None  # the stage's packed state (large arrays in `arrays`, by digest)
    covers: int = 0  # the jobs submitted before it (numbers 1..covers) are in it, done or queued
    arrays: dict[str, bytes] = field(default_factory=dict)


class RestartLog:
    """The newest checkpoint, the arrays it and the cuts asked for refer to, and the jobs after it (not
    thread-safe: the proxy holds its wire lock around every call)."""

    def __init__(self) -> None:
        self.checkpoint = Checkpoint()
        self._arrays: dict[str, bytes] = {}  # large arrays of the checkpoint and of the cuts asked for, by digest
        self._pinned: dict[int, set[str]] = {}  # per cut asked for: the arrays it was told are held here
        self._jobs: deque[tuple[int, Job]] = deque()  # (submission number, job) after the checkpoint

    def record(self, number: int, job: Job) -> None:
        """Job `number` was submitted."""
        self._jobs.append((number, job))

    def jobs(self) -> list[Job]:
        """The jobs a process that loads the checkpoint is sent again, in order."""
        return [job for _, job in self._jobs]

    def start_from(self, data: bytes, covers: int) -> None:
        """A restored session's map part is the checkpoint now, covering `covers` jobs."""
        self.checkpoint = Checkpoint(data, covers, {})
        self._drop_through(covers)

    def held_for(self, call_id: int) -> list[str]:
        """The digests cut `call_id` need not send (held here until its reply comes)."""
        self._pinned[call_id] = set(self._arrays)
        return sorted(self._pinned[call_id])

    def forget(self, call_id: int) -> None:
        """Cut `call_id` failed: its arrays need not be held for it."""
        self._pinned.pop(call_id, None)

    def complete(self, call_id: int, reply: dict[str, Any], covers: int) -> tuple[Checkpoint, bool]:
        """The reply to cut `call_id`, covering `covers` jobs, as a checkpoint; whether it became the newest (a
        cut overtaken by a later one does not). RuntimeError when it refers to arrays not held here."""
        self._pinned.pop(call_id, None)
        self._arrays.update(reply["arrays"])
        missing = [d for d in reply["digests"] if d not in self._arrays]
        if missing:
            raise RuntimeError(f"the mapping process's snapshot refers to {len(missing)} arrays not held here")
        checkpoint = Checkpoint(reply["bytes"], covers, {d: self._arrays[d] for d in reply["digests"]})
        newest = covers >= self.checkpoint.covers  # a restart reads the checkpoint and the jobs after it as one
        if newest:
            self.checkpoint = checkpoint
            self._drop_through(covers)
        keep = set(self.checkpoint.arrays).union(*self._pinned.values())
        self._arrays = {d: a for d, a in self._arrays.items() if d in keep}
        return checkpoint, newest

    def _drop_through(self, covers: int) -> None:
        while self._jobs and self._jobs[0][0] <= covers:
            self._jobs.popleft()
