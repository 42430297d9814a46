"""A live session's tracking state for the fleet view, read from the tail of its outbox (the stream's messages).

The worker reports pose-source events (tracking_lost, relocalized, initialized) as messages, not in the session
record; the newest of them in the last OUTBOX_TAIL messages says whether the camera is lost. Older than that (a
camera lost for more than OUTBOX_TAIL frames) reads as "tracking": the figure is a fleet overview, the events
themselves are exact.
"""

from __future__ import annotations

from typing import Literal

import redis.asyncio as aioredis

from worker.runtime import keys

TrackingState = Literal["waiting", "tracking", "lost"]
OUTBOX_TAIL = 256
_LOST = '{"type": "tracking_lost"'
_BACK = ('{"type": "relocalized"', '{"type": "initialized"')
LIVE = ("created", "streaming", "finishing", "abandoned")


async def tracking_states(client: aioredis.Redis, sessions: list[dict]) -> dict[str, TrackingState]:
    """{session id: state} for the live sessions among `sessions` (API dicts); one pipelined round trip."""
    live = [s for s in sessions if s["status"] in LIVE]
    if not live:
        return {}
    pipe = client.pipeline(transaction=False)
    for s in live:
        pipe.xrevrange(keys.outbox(s["id"]), count=OUTBOX_TAIL)
    states: dict[str, TrackingState] = {}
    for s, entries in zip(live, await pipe.execute()):
        state: TrackingState = "tracking" if s["frames_processed"] > 0 else "waiting"
        for _, fields in entries:  # newest first
            text = fields.get(b"msg", b"").decode(errors="replace")
            if text.startswith(_LOST):
                state = "lost"
                break
            if text.startswith(_BACK):
                break
        states[s["id"]] = state
    return states
