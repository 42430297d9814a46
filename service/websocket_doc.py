"""The WebSocket protocol, as the `x-websocket` extension of openapi.yaml (OpenAPI cannot describe WebSockets).

A client written from this text alone must be able to stream without probing the server: every message, error
code, close code, the flow-control rules and the session's lifetime are stated here.
"""

from __future__ import annotations

from typing import Any

from protocol.limits import DEFAULT_MAX_QUEUE, MAX_FRAME_BYTES
from protocol.messages import (
    CLIENT_MESSAGES,
    CLOSE_CODES,
    ERROR_CODES,
    SERVER_MESSAGES,
    AckMessage,
    PongMessage,
)
from protocol.schema import message_schema

FRAME_ERROR_CODES = ERROR_CODES  # the name tests and older imports use
# what the gateway answers itself on the stream, not forwarded from the session's outbox to the events feed
_STREAM_ONLY = {AckMessage.TYPE, PongMessage.TYPE}


def _client_messages() -> dict[str, Any]:
    out = {}
    for name, kind in CLIENT_MESSAGES.items():
        entry: dict[str, Any] = {"encoding": kind.ENCODING, "schema": message_schema(kind, with_description=False)}
        if kind.DOC:
            entry["description"] = kind.DOC
        out[name] = {**entry, **kind.NOTES}
    return out


def _server_messages() -> dict[str, Any]:
    return {"encoding": "text JSON", **{name: message_schema(kind) for name, kind in SERVER_MESSAGES.items()}}


WEBSOCKET_DOC = {
    "/v1/sessions/{session_id}/stream": {
        "summary": "Stream camera frames; receive acks, live poses and loop-closure events",
        "auth": "X-API-Key or Authorization: Bearer header, or ?api_key= query parameter; needs the stream scope "
                "and the key that created the session (or admin). A server started without keys "
                "(FLASHMONO_API_KEYS unset) is open to anyone and logs a warning saying so at start-up.",
        "closing": "Every close other than 1000 and 1009 comes right after an `error` message with a `code` and a "
                   "`message` saying why. Close codes: see close_codes.",
        "close_codes": CLOSE_CODES,
        "flow_control": (
            "Each binary frame gets exactly one immediate answer, in the order frames arrived: `ack` (queued "
            "durably) or `error` with its seq (not queued, or unusable). Each acked frame later gets exactly one "
            "result with its seq: `pose` (processed) or `error` (the worker could not use it). A windowed sender "
            "therefore counts frames at the server as acks minus results, and frames on the wire as sent minus "
            "immediate answers; neither count can stall. Backpressure keeps the order: once frame N is refused "
            "with `backpressure`, every later seq is refused the same way with `resend_from: N`, even after the "
            "queue drains, until a frame with seq <= N is accepted; so rewind to N, wait a little (back off "
            "exponentially while refusals go on) and re-send from there, ignoring the refusals of frames sent "
            "before the rewind. A live camera that prefers fresh images may send its newest image under seq N."),
        "sequence_numbers": "seq must increase strictly within a session; gaps are allowed (a skipped seq is never "
                            "waited for). A seq at or below the last accepted one is refused with bad_seq.",
        "session_lifetime": (
            "Closing the socket without `finish` leaves the session live (status streaming) with its queue and "
            "results; nothing times it out. Reconnect to the same URL and go on with seqs above the last acked one "
            "(a bad_seq error names it); results already sent are not repeated, GET the trajectory for them. "
            "`finish` (from any connection) ends it; DELETE /v1/sessions/{id} discards it."),
        "client_messages": _client_messages(),
        "server_messages": _server_messages(),
        "limits": f"frame messages up to FLASHMONO_MAX_FRAME_BYTES ({MAX_FRAME_BYTES // 2**20} MiB); at most "
                  f"FLASHMONO_MAX_QUEUE ({DEFAULT_MAX_QUEUE}) frames queued per session",
    },
    "/v1/sessions/{session_id}/events": {
        "description": "A read-only feed for viewers that do not send the frames (the web viewer): the messages the "
                       "session's stream gets ("
                       + ", ".join(name for name in SERVER_MESSAGES if name not in _STREAM_ONLY) + ") "
                       "from the "
                       "moment of connection; the trajectory endpoint has the earlier ones. A session already "
                       "finished or failed answers one `finished`/`failed` message. Same authentication as the "
                       "stream (read or stream scope; ?api_key= allowed).",
        "client_messages": {},
        "server_messages": "as the stream's server_messages, without ack and pong",
        "close_codes": {"1000": "after finished", "4401": "unknown or missing API key", "4403": "not allowed",
                        "4404": "no such session, or it was deleted"},
    },
}
