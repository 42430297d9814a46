"""Where a session's finish is: its phase, the work done and left in it, and an estimate of the time left.

`SlamSystem.finish()` moves it through its phases (draining the mapping stage, closing the last loops, the final
refinement); `flashmono run` and the worker's `finishing` messages read it from another thread while finish runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

PHASES = ("mapping", "loop_closing", "refining", "done")


class FinishStatus:
    """The finish's progress; written by the finishing thread, read by any (plain attributes, no lock needed)."""

    def __init__(self) -> None:
        self.phase: str | None = None  # None: not finishing
        self.total = 0
        self._done = 0
        self._done_of: Callable[[], int] | None = None
        self._started = 0.0
        self._phase_started = 0.0
        self._deadline: float | None = None

    def begin(self, phase: str, total: int, done: Callable[[], int] | None = None,
              deadline: float | None = None) -> None:
        """Enter `phase` with `total` units of work; `done` counts them when the phase cannot (a stage draining);
        `deadline` (perf_counter) ends the phase whatever is left."""
        if phase not in PHASES:
            raise ValueError(f"unknown finish phase {phase!r}")
        now = time.perf_counter()
        if self.phase is None:
            self._started = now
        self.phase, self.total, self._done, self._done_of = phase, max(0, int(total)), 0, done
        self._phase_started, self._deadline = now, deadline

    def step(self, units: int = 1) -> None:
        """`units` more of the phase's work are done."""
        self._done += units

    @property
    def done(self) -> int:
        done = self._done_of() if self._done_of is not None else self._done
        return max(0, min(self.total, int(done)))

    def eta_s(self) -> float | None:
        """Seconds the current phase still needs at its pace so far (bounded by its deadline); None: no pace yet."""
        if self.phase in (None, "done"):
            return 0.0 if self.phase == "done" else None
        now = time.perf_counter()
        left = None
        done = self.done
        if done > 0 and self.total:
            left = (now - self._phase_started) / done * (self.total - done)
        if self._deadline is not None:
            until = max(0.0, self._deadline - now)
            left = until if left is None else min(left, until)
        return left

    def as_dict(self) -> dict[str, Any]:
        """{phase, done, total, elapsed_s, eta_s} for messages and progress bars."""
        eta = self.eta_s()
        return {"phase": self.phase, "done": self.done, "total": self.total,
                "elapsed_s": round(time.perf_counter() - self._started, 1) if self.phase else 0.0,
                "eta_s": None if eta is None else round(eta, 1)}
