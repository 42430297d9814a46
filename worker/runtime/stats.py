"""Per-stage latency figures of one worker, published to Redis for the gateway's /metrics and the benchmark."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from protocol.keys import WORKER_STAGES

STAGES = WORKER_STAGES


class StageStats:
    """Thread-safe running sums, counts and a window of recent samples per stage (seconds)."""

    def __init__(self, window: int = 2000) -> None:
        self._lock = threading.Lock()
        self._sum = dict.fromkeys(STAGES, 0.0)
        self._count = dict.fromkeys(STAGES, 0)
        self._recent = {stage: deque(maxlen=window) for stage in STAGES}

    def add(self, stage: str, seconds: float, count: int = 1) -> None:
        with self._lock:
            self._sum[stage] += seconds
            self._count[stage] += count
            self._recent[stage].append(seconds / max(count, 1))

    def as_fields(self) -> dict[str, float]:
        """Flat {stage_sum, stage_count, stage_p50, stage_p99} for a Redis hash."""
        with self._lock:
            out: dict[str, float] = {}
            for stage in STAGES:
                out[f"{stage}_sum"] = self._sum[stage]
                out[f"{stage}_count"] = self._count[stage]
                if self._recent[stage]:
                    values = np.fromiter(self._recent[stage], dtype=np.float64)
                    out[f"{stage}_p50"] = float(np.percentile(values, 50))
                    out[f"{stage}_p99"] = float(np.percentile(values, 99))
            return out
