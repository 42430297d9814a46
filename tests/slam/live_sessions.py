"""Threaded sessions for the live-engine tests: an RGB-D configuration with a keyframe every 2 frames, and pushing
frames from another thread within a deadline (tracking must never wait for mapping)."""

from __future__ import annotations

import threading

from worker.config import SlamConfig
from worker.data import Frame
from worker.slam import SlamSystem


def live_config(**overrides) -> SlamConfig:
    """RGB-D odometry (no poses), every stage in its own thread, a keyframe every 2 frames; `overrides` merge into
    its sections."""
    base = {"input": {"surfel_init": "depth"}, "frontend": {"keyframe_every": 2}, "threaded": True}
    for key, value in overrides.items():
        base[key] = {**base.get(key, {}), **value} if isinstance(value, dict) else value
    return SlamConfig.preset("test", **base)


def push_all_within(system: SlamSystem, frames: list[Frame], timeout_s: float = 120.0) -> list:
    """Push `frames` from another thread; fails if tracking does not get through them (it waited for mapping)."""
    results: list = []
    pusher = threading.Thread(target=lambda: results.extend(system.push(f) for f in frames), daemon=True)
    pusher.start()
    pusher.join(timeout_s)
    assert not pusher.is_alive(), "tracking waited for mapping"
    return results
