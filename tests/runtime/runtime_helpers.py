"""Runtime tests: real redis-server, gateway and worker processes (the passthrough engine keeps them fast)."""

from __future__ import annotations

import time

import cv2
import msgpack
import numpy as np
from live_stack import receive_until  # noqa: F401  (re-exported for this area's tests)

WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LEASE_TTL_MS": "4000", "FLASHMONO_SNAPSHOT_EVERY": "2",
              "FLASHMONO_LOG_LEVEL": "INFO"}


def synthetic_frame(seq: int, width: int = 64, height: int = 48) -> bytes:
    """A wire frame message with a small JPEG and a pose prior that encodes the seq (x translation = seq)."""
    image = np.full((height, width, 3), (seq * 7) % 256, np.uint8)
    pose = np.eye(4)
    pose[0, 3] = float(seq)
    return msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30.0,
                          "image": cv2.imencode(".jpg", image)[1].tobytes(), "pose": pose.reshape(-1).tolist()})


def wait_for(condition, timeout_s: float = 60.0, interval_s: float = 0.05):
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met in time")
        time.sleep(interval_s)
