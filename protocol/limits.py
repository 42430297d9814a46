"""Sizes the gateway enforces and the engine honours, each defined once.

The gateway's settings (FLASHMONO_MAX_FRAME_BYTES, FLASHMONO_MAX_RENDER_PIXELS) default to these; the hard bounds
(image side, render side, seq) are not configurable.
"""

from __future__ import annotations

MAX_FRAME_BYTES = 8 * 1024 * 1024
"""Default bound of one binary frame message (FLASHMONO_MAX_FRAME_BYTES)."""

MAX_IMAGE_SIDE = 8192
"""Longest side, in pixels, of a streamed image and of a session's declared intrinsics."""

MIN_RENDER_SIDE = 8
MAX_RENDER_SIDE = 4096
"""Bounds of each side of a render request (GET .../render); the engine must accept every size within them."""

MAX_RENDER_PIXELS = MAX_RENDER_SIDE * MAX_RENDER_SIDE
"""Default bound of width x height of one render (FLASHMONO_MAX_RENDER_PIXELS)."""

MAX_SEQ = 2**53
"""Frame seqs lie in [0, MAX_SEQ): every JSON number up to it is an exact integer, in every client language."""

DEFAULT_MAX_QUEUE = 64
"""Default of FLASHMONO_MAX_QUEUE: frames queued per session before `backpressure`."""


def websocket_max_size(max_frame_bytes: int = MAX_FRAME_BYTES) -> int:
    """The WebSocket layer's message bound for a frame bound: room for a frame message over the limit to reach the
    gateway and be answered `too_large` instead of the socket closing with 1009."""
    return max_frame_bytes * 2 + 1024

MAX_MAP_PACKAGE_BYTES = 256 * 1024 * 1024
"""Default bound of one map package (protocol.map_package), uploaded or made from a session
(FLASHMONO_MAX_MAP_BYTES)."""

MAX_MAP_KEYFRAMES = 20_000
"""Keyframes one map package may hold."""
