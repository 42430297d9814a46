"""WS /v1/sessions/{id}/stream: frames in (binary msgpack), acks/poses/events out (text JSON).

The receive loop validates each frame, enqueues it with one atomic Redis call (seq check + bounded queue) and
acks it; a forwarding task relays the worker's results from the session's outbox stream.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time

from fastapi import APIRouter, HTTPException, WebSocket, WebSocketDisconnect

from protocol.messages import AckMessage, ErrorCode, ErrorMessage, PongMessage
from service.auth import request_key
from service.deps import session_for
from service.frame_validation import FrameRejected, check_frame_message
from service.hardening import origin_allowed
from service.outbox_hub import SESSION_DELETED, OutboxHub
from service.registry import (
    INGEST_ACCEPTED,
    NO_SESSION,
    NOT_ACCEPTING,
    QUEUE_FULL,
    SEQ_NOT_INCREASING,
    SIZE_MISMATCH,
    IngestResult,
    Registry,
)
from worker.runtime.outage import REDIS_DOWN

log = logging.getLogger(__name__)
router = APIRouter()

_AUTH_CODES = {401: "unauthorized", 403: "forbidden", 404: "not_found"}


@router.websocket("/v1/sessions/{session_id}/stream")
async def stream_frames(websocket: WebSocket, session_id: str) -> None:
    app = websocket.app
    reg: Registry = app.state.registry
    origin = websocket.headers.get("origin")
    if not origin_allowed(origin, websocket.headers.get("host"), app.state.settings.allowed_origins):
        await _refuse(websocket, "forbidden_origin", f"Origin {origin} may not open streams here (set "
                      "FLASHMONO_ALLOWED_ORIGINS to allow it)", 4403)
        return
    try:
        principal = app.state.auth.principal(request_key(websocket, allow_query=True))
        app.state.auth.require(principal, "stream")
        record = await session_for(reg, principal, session_id, write=True)
    except REDIS_DOWN as err:
        await _refuse(websocket, "unavailable", f"the session store (Redis) is unreachable: {err}; reconnect "
                      "shortly", 1013)
        return
    except HTTPException as err:
        await _refuse(websocket, _AUTH_CODES.get(err.status_code, "error"), str(err.detail), 4000 + err.status_code)
        return
    if record["status"] == "abandoned":
        grace = app.state.settings.abandoned_grace_s
        if await reg.revive(session_id, grace) == 1:
            record["status"] = "streaming"
        else:
            record["error"] = f"it was abandoned (no frames) more than {grace:g} s ago and can no longer be resumed"
    if record["status"] not in ("created", "streaming"):
        why = f": {record['error']}" if record["status"] == "abandoned" else ""
        await _refuse(websocket, "not_accepting", f"session is {record['status']}; it takes no frames{why}", 4409)
        return
    limit = app.state.settings.max_streams
    if app.state.outbox_hub.streams >= limit:
        await _refuse(websocket, "too_many_streams", f"this gateway has {limit} open streams, its limit "
                      "(FLASHMONO_MAX_STREAMS); retry shortly or on another one", 1013)
        return
    await websocket.accept()
    stream = _Stream(websocket, reg, session_id, json.loads(record.get("intrinsics") or "null"))
    await stream.run()


async def _refuse(websocket: WebSocket, code: str, message: str, close_code: int) -> None:
    """Turn a stream away: accept, one error message saying why, then `close_code`."""
    await websocket.accept()
    await websocket.send_text(ErrorMessage(code=code, message=message).to_json())
    await websocket.close(code=close_code, reason=message.encode()[:120].decode(errors="ignore"))


def _int_or_none(value) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _backpressure_message(seq: int, depth: int, resend_from: int) -> str:
    if seq == resend_from:
        return f"session queue is full ({depth} frames); frame {seq} was not queued: resend it later"
    return (f"frame {seq} was not queued: frame {resend_from} was refused for backpressure and must be re-sent "
            f"first (the queue holds {depth} frames); resend from seq {resend_from}")


class _Stream:
    """One open stream of one session."""

    def __init__(self, websocket: WebSocket, reg: Registry, session_id: str, intrinsics: dict | None) -> None:
        self.ws = websocket
        self.reg = reg
        self.session_id = session_id
        self.intrinsics = intrinsics
        self.settings = websocket.app.state.settings
        self.metrics = websocket.app.state.metrics
        self._send_lock = asyncio.Lock()
        self._closed = asyncio.Event()
        self._unavailable_from: int | None = None  # first seq refused while Redis was unreachable

    async def send(self, text: str) -> None:
        async with self._send_lock:
            await self.ws.send_text(text)

    async def error(self, code: ErrorCode, message: str, seq: int | None = None, **extra: int) -> None:
        await self.send(ErrorMessage(code=code, message=message, seq=seq, **extra).to_json())

    async def run(self) -> None:
        self.metrics.streams_open.inc()
        try:
            start_id = await self.reg.last_outbox_id(self.session_id)
        except REDIS_DOWN as err:
            self.metrics.streams_open.dec()
            await self.error("unavailable", f"the session store (Redis) is unreachable: {err}; reconnect shortly")
            await self._close(1013)
            return
        forwarder = asyncio.create_task(self._forward_results(start_id))
        try:
            while not self._closed.is_set():
                message = await self.ws.receive()
                if message["type"] == "websocket.disconnect":
                    break
                if message.get("bytes") is not None:
                    await self._on_frame(message["bytes"])
                elif message.get("text") is not None:
                    await self._on_control(message["text"])
        except (WebSocketDisconnect, RuntimeError):
            pass  # the client went away (RuntimeError: receive after the forwarder closed the socket)
        finally:
            self.metrics.streams_open.dec()
            forwarder.cancel()
            try:
                await forwarder
            except (asyncio.CancelledError, Exception):
                pass

    async def _on_frame(self, data: bytes) -> None:
        t0 = time.perf_counter()
        try:
            frame = check_frame_message(data, self.settings.max_frame_bytes, self.intrinsics)
        except FrameRejected as err:
            self.metrics.frames_refused.labels(err.code).inc()
            await self.error(err.code, str(err), err.seq)
            return
        result = await self._ingest(frame.seq, data, f"{frame.width}x{frame.height}")
        if result is None:
            return
        if result.code == QUEUE_FULL:
            self.metrics.frames_refused.labels("backpressure").inc()
            await self.error("backpressure", _backpressure_message(frame.seq, result.value, result.resend_from),
                             frame.seq, queue_depth=result.value, resend_from=result.resend_from)
        elif result.code == SEQ_NOT_INCREASING:
            self.metrics.frames_refused.labels("bad_seq").inc()
            await self.error("bad_seq", f"seq {frame.seq} is not greater than the last accepted seq {result.value} "
                             "(duplicate or out of order); frame not queued", frame.seq)
        elif result.code == SIZE_MISMATCH:
            self.metrics.frames_refused.labels("bad_size").inc()
            await self.error("bad_size", f"image is {frame.width}x{frame.height} but this session's frames are "
                             f"{result.frame_size} (its first frame's size); frame not queued", frame.seq)
        elif result.code == NOT_ACCEPTING:
            await self.error("not_accepting", "the session is finishing or finished; frame not queued", frame.seq)
        elif result.code == NO_SESSION:
            await self.error("not_found", "the session was deleted", frame.seq)
            await self._close(4404)
        else:
            await self.send(AckMessage(seq=frame.seq, queue_depth=result.value).to_json())
            self.metrics.frames_ingested.inc()
            self.metrics.queue_depth.observe(result.value)
            self.metrics.ack_latency.observe(time.perf_counter() - t0)
            if result.started:
                await self._wake_a_worker()

    async def _wake_a_worker(self) -> None:
        """The session's first frame is queued: a job now, so that a worker starts it at once (its first job waits,
        deferred, for the worker's next look at sessions without frames: up to a second of the first pose's
        latency). Without Redis the deferred job still starts it."""
        try:
            await self.reg.queue_job(self.session_id)
        except REDIS_DOWN as err:
            log.warning("session %s: its first frame is queued but no worker was woken (%s): it starts at the "
                        "next check", self.session_id, err)

    async def _ingest(self, seq: int, data: bytes, frame_size: str):
        """The registry's answer for this frame, or None after refusing it with `unavailable` (Redis down).

        Like backpressure, the refusal keeps the order: once a frame is refused, later ones are refused too until
        it comes again, so the client re-sends from it and nothing is queued out of order."""
        hold = self._unavailable_from
        outcome_unknown = hold == seq  # its last attempt failed in flight: it may have been queued all the same
        if hold is not None and seq > hold:
            await self.error("unavailable", f"frame {seq} was not queued: frame {hold} was refused while the "
                             f"session store was unreachable; resend from seq {hold}", seq, resend_from=hold)
            return None
        try:
            result = await self.reg.ingest_frame(self.session_id, seq, data, self.settings.max_queue, frame_size)
        except REDIS_DOWN as err:
            self._unavailable_from = seq
            self.metrics.frames_refused.labels("unavailable").inc()
            await self.error("unavailable", f"the session store (Redis) is unreachable ({err}); frame {seq} was "
                             "not queued: resend it later", seq, resend_from=seq)
            return None
        self._unavailable_from = None
        if outcome_unknown and result.code == SEQ_NOT_INCREASING and result.value == seq:
            # the attempt refused as `unavailable` had been queued before the connection broke (e.g. a cluster
            # primary failing over): ack it now, once, rather than refuse the re-send as a duplicate
            return IngestResult(INGEST_ACCEPTED, max(result.queue_depth, 0))
        return result

    async def _on_control(self, text: str) -> None:
        try:
            message = json.loads(text)
        except ValueError:
            await self.error("bad_message", "text messages must be JSON objects like {\"type\": \"finish\"}; "
                             "frames go in binary messages (msgpack maps)")
            return
        kind = message.get("type") if isinstance(message, dict) else None
        if kind == "frame":
            await self.error("bad_message", "frames must be binary WebSocket messages holding a msgpack map "
                             "(image as raw bytes), not text JSON; frame not queued", _int_or_none(message.get("seq")))
        elif kind == "ping":
            await self.send(PongMessage().to_json())
        elif kind == "finish":
            try:
                outcome = await self.reg.request_finish(self.session_id)
            except REDIS_DOWN as err:
                await self.error("unavailable", f"the session store (Redis) is unreachable ({err}); the finish "
                                 "request was not recorded: send it again later")
                return
            if outcome == -1:
                await self.error("not_found", "the session was deleted")
                await self._close(4404)
        else:
            await self.error("bad_message", f"unknown control message type {kind!r}; expected finish or ping")

    async def _forward_results(self, last_id: str) -> None:
        """Relay the outbox (pose, loop_closed, error, finished) to the client; close after "finished".

        The gateway's one OutboxHub reads every stream's outbox (one Redis connection for all streams, surviving
        outages and stalls); this task only forwards this stream's entries, at the client's pace."""
        hub: OutboxHub = self.ws.app.state.outbox_hub
        subscription = hub.subscribe(self.session_id, last_id)
        try:
            while True:
                text = await subscription.queue.get()
                if text is SESSION_DELETED:
                    await self.error("not_found", "the session was deleted")
                    await self._close(4404)
                    return
                await self.send(text)  # each seq appears once: the worker's store is idempotent
                if text.startswith('{"type": "finished"'):
                    await self._close(1000)
                    return
        finally:
            hub.unsubscribe(subscription)

    async def _close(self, code: int) -> None:
        self._closed.set()
        async with self._send_lock:
            try:
                await self.ws.close(code=code)
            except RuntimeError:
                pass
