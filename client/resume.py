"""Resuming a stream after its connection broke (a gateway restarted, a network change): what the server already
has, and how the client's flow control catches up with it.

The server's record is the truth: frames up to the session's `last_seq` are queued durably (their acks may have
been lost with the connection); results published while no socket was open are in the trajectory. Frames sent
after `last_seq` never arrived and are re-sent under their own seq, in order, so nothing is lost or renumbered.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import httpx

from client.streaming import FlowControl


@dataclass(frozen=True)
class ResumePoint:
    """The server's view of a session: its status, the last accepted seq, and the results stored so far."""

    status: str
    last_seq: int
    poses: list[dict[str, Any]] = field(default_factory=list)  # trajectory entries {seq, timestamp, pose, ...}
    keyframes: frozenset[int] = frozenset()
    revision: int = 0


async def fetch_resume_point(http: httpx.AsyncClient, session_id: str, with_results: bool = True) -> ResumePoint:
    """GET the session (and, with results, its trajectory and keyframes) over REST; httpx errors propagate."""
    response = await http.get(f"/v1/sessions/{session_id}")
    response.raise_for_status()
    session = response.json()
    point = ResumePoint(status=str(session["status"]), last_seq=int(session.get("last_seq", -1)),
                        revision=int(session.get("revision") or 0))
    if not with_results:
        return point
    poses = await http.get(f"/v1/sessions/{session_id}/trajectory")
    keyframes = await http.get(f"/v1/sessions/{session_id}/trajectory", params={"which": "keyframes"})
    poses.raise_for_status()
    keyframes.raise_for_status()
    return ResumePoint(status=point.status, last_seq=point.last_seq, poses=poses.json()["poses"],
                       keyframes=frozenset(p["seq"] for p in keyframes.json()["poses"]), revision=point.revision)


def reconcile(flow: FlowControl, point: ResumePoint) -> tuple[list[tuple[int, Any]], list[dict[str, Any]]]:
    """Bring `flow` in line with the server after a reconnect.

    Frames in flight up to `point.last_seq` count as acknowledged; later ones leave the flow control and are
    returned, in seq order, to be re-sent under the same seq. Returns (re-sends, pose messages for the frames
    whose results were stored while disconnected), the latter shaped like the server's live "pose" messages.
    """
    resend: list[tuple[int, Any]] = []
    for seq in sorted(flow.in_flight):
        if seq <= point.last_seq:
            flow.on_ack(seq)
        else:
            flow.in_flight.discard(seq)
            resend.append((seq, flow.items.pop(seq)))
    by_seq = {int(p["seq"]): p for p in point.poses}
    missed = []
    for seq in sorted(flow.pending):
        if seq in by_seq:
            entry = by_seq[seq]
            missed.append({"type": "pose", "seq": seq, "timestamp": entry["timestamp"], "pose": entry["pose"],
                           "scale": entry.get("scale", 1.0), "is_keyframe": seq in point.keyframes,
                           "revision": point.revision})
    return resend, missed
