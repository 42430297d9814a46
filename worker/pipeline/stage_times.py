"""The SLAM system's runtime breakdown (paper appendix E, Table 8): wall time per module, per thread.

Per-frame modules (frontend inference, loop detection, merge and voxelization, refinement) are reported per frame;
sparse events (loop-frame feed-forward, PGO, map loop correction) per event, as the paper does.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

# stage -> (thread, description, per frame or per event)
STAGES: dict[str, tuple[str, str, str]] = {
    "frontend_tracking": ("frontend", "geometric tracking (odometry)", "frame"),
    "frontend_inference": ("frontend", "feed-forward inference (tracking)", "frame"),
    "loop_detection": ("frontend", "loop closure detection", "frame"),
    "loop_relocalization": ("frontend", "loop frame relocalization", "event"),
    "keyframe_alignment": ("frontend", "dense alignment of keyframes to their neighbours (RGB-D)", "event"),
    "pgo": ("frontend", "PGO (Sim(3) optimization)", "event"),
    "map_relocalization": ("frontend", "finding frames in a stored map", "event"),
    "map_depth": ("backend", "multi-view depth of keyframes", "event"),
    "map_merge": ("backend", "merge & voxelization (fusion, pruning)", "frame"),
    "map_refine": ("backend", "refine", "frame"),
    "map_loop_correction": ("backend", "GS loop correction", "event"),
    "map_catch_up": ("backend", "refinement shed earlier, caught up while idle", "event"),
    "map_final_refine": ("backend", "final refinement (at finish)", "event"),
}


class StageTimes:
    """Thread-safe running wall-time totals and counts per stage of `STAGES`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self.counts = dict.fromkeys(STAGES, 0)

    def add(self, stage: str, seconds: float) -> None:
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; known: {', '.join(STAGES)}")
        with self._lock:
            self.seconds[stage] += seconds
            self.counts[stage] += 1

    def set_total(self, stage: str, seconds: float, count: int) -> None:
        """Set `stage`'s totals (a stage timed in another process reports them)."""
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; known: {', '.join(STAGES)}")
        with self._lock:
            self.seconds[stage], self.counts[stage] = float(seconds), int(count)

    @contextmanager
    def measure(self, stage: str) -> Iterator[None]:
        """Time the body of a `with` block as one event of `stage`."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(stage, time.perf_counter() - start)

    def breakdown(self, frames: int) -> dict[str, dict[str, float | int | str]]:
        """Per stage: thread, total seconds, events, ms per event and ms per frame (over `frames` frames)."""
        with self._lock:
            return {stage: {"thread": thread, "total_s": self.seconds[stage], "events": self.counts[stage],
                            "ms_per_event": 1e3 * self.seconds[stage] / self.counts[stage] if self.counts[stage]
                            else 0.0,
                            "ms_per_frame": 1e3 * self.seconds[stage] / frames if frames else 0.0}
                    for stage, (thread, _, _) in STAGES.items()}


def breakdown_table(breakdown: dict[str, dict], frames: int) -> str:
    """A markdown table shaped like the paper's Table 8 (per-frame modules per frame, sparse ones per event)."""
    lines = ["| thread | module | time (ms) | note |", "|---|---|---:|---|"]
    for thread in ("frontend", "backend"):
        per_frame = 0.0
        for stage, (owner, description, unit) in STAGES.items():
            if owner != thread:
                continue
            row = breakdown[stage]
            if unit == "frame":
                per_frame += row["ms_per_frame"]
                lines.append(f"| {thread} | {description} | {row['ms_per_frame']:.1f} | per frame ({frames} frames) |")
            else:
                lines.append(f"| {thread} | {description} | {row['ms_per_event']:.1f} | per event "
                             f"({row['events']} events) |")
        lines.append(f"| {thread} | **total per frame** | {per_frame:.1f} | |")
    return "\n".join(lines)
