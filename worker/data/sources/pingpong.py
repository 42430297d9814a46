"""A recorded sequence played forward, backward, forward, ...: a long session that keeps coming back to the places
it has seen (`open_source(path, pingpong=N)`, `flashmono run --pingpong N`).

Frame indices keep increasing across the sweeps (0 .. N x (len - 1)) and so do the timestamps (one median frame
period apart); the turning frames are not repeated. Ground truth, depth and intrinsics come with every frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from worker.data.frame import Frame

from .base import DatasetError, FrameSource, RecordedSource


def sweep_order(count: int, sweeps: int) -> list[int]:
    """Positions in the recording for `sweeps` sweeps over `count` frames (the turning frames played once)."""
    if sweeps < 1:
        raise DatasetError(f"pingpong must be >= 1 sweeps, got {sweeps}")
    forward = list(range(count))
    order = forward[:]
    for sweep in range(1, sweeps):
        order += (forward[::-1] if sweep % 2 else forward)[1:]
    return order


class PingPongSource(FrameSource):
    """`sweeps` sweeps of a recorded sequence, forward and back in turn (see the module docstring)."""

    def __init__(self, source: FrameSource, sweeps: int) -> None:
        if not isinstance(source, RecordedSource):
            raise DatasetError("pingpong plays recorded datasets (folders), not videos, cameras or synthetic streams")
        super().__init__(source.options)
        self.source, self.sweeps = source, int(sweeps)
        self.name = f"{source.name} x{self.sweeps} pingpong"
        self.intrinsics = source.intrinsics
        stamps = np.array([r.timestamp for r in source.records], np.float64)
        steps = np.diff(stamps)
        self._period = float(np.median(steps)) if len(steps) and np.median(steps) > 0 else 1.0 / 30.0
        self._start = float(stamps[0])
        self._order = sweep_order(len(source), self.sweeps)

    def __len__(self) -> int:
        return len(self._order)

    def __iter__(self) -> Iterator[Frame]:
        records = self.source.records
        for index, position in enumerate(self._order):
            frame = self.source._load(position, records[position])
            yield replace(frame, index=index, timestamp=self._start + index * self._period)
