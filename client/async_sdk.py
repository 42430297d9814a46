"""The asynchronous Python SDK: `AsyncFlashMonoClient` (REST over httpx) and `AsyncFrameStream` (the WebSocket).

    async with AsyncFlashMonoClient("http://localhost:8000", api_key="...") as client:
        session = await client.create_session(name="walk", intrinsics={"fx": 525, ...})
        async with client.open_stream(session.id) as stream:
            for frame in frames:
                await stream.send(frame)
            async for event in stream.events():   # or on_event=callback
                ...
            summary = await stream.finish()
        trajectory = await client.trajectory(session.id)
"""

from __future__ import annotations

import asyncio
import inspect
import json
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np

from client import rest
from client.errors import (
    FlashMonoError,
    ServerError,
    ServerUnreachableError,
    StreamError,
    error_for_status,
    stream_error_from_frame,
)
from client.frames import FrameLike
from client.models import (
    InputEvent,
    LoopClosedEvent,
    MapInfo,
    MapPage,
    PoseEvent,
    Session,
    SessionPage,
    StreamEvent,
    StreamSummary,
    TrackingEvent,
    Trajectory,
    stream_event,
)
from client.resume import ResumePoint, fetch_resume_point, reconcile
from client.streaming import FlowControl, WireOptions, encode_frame_message, open_frames
from protocol.messages import AckMessage, ErrorMessage, FinishedMessage, SkippedMessage, parse_server_message

EventCallback = Callable[[StreamEvent], Any]
# Error codes with which the gateway refuses a whole stream, and the HTTP status they stand for.
_REFUSAL_STATUS = {"unauthorized": 401, "forbidden": 403, "not_found": 404}
# Close codes after which re-opening the stream cannot help (auth, no such session, takes no frames).
_FINAL_CLOSE_CODES = (4401, 4403, 4404, 4409)
DEFAULT_SERVER = "http://127.0.0.1:8000"


def websocket_url(server_url: str, path: str) -> str:
    """ws(s):// URL of `path` on the server at http(s)://`server_url`."""
    base = server_url.rstrip("/")
    if base.startswith("https://"):
        return "wss://" + base[len("https://"):] + path
    if base.startswith("http://"):
        return "ws://" + base[len("http://"):] + path
    if base.startswith(("ws://", "wss://")):
        return base + path
    raise ValueError(f"server URL must start with http:// or https://, got {server_url!r}")


def decode_png(data: bytes, kind: str = "color") -> np.ndarray:
    """A rendered PNG as an array: RGB uint8 [H, W, 3] for color, metres float32 [H, W] for 16-bit depth (mm)."""
    import cv2

    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("the server's answer is not a decodable PNG")
    if kind == "depth":
        return image.astype(np.float32) / 1000.0
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    return cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB)


def _json_or_text(response: httpx.Response) -> Any:
    try:
        return response.json()
    except ValueError:
        return response.text


class AsyncFrameStream:
    """One WebSocket stream of frames into a session, with flow control and live events.

    Use as an async context manager (or call `connect()` / `close()`). `send(frame)` waits while the flow
    control says the server has enough frames; `events()` yields PoseEvent / LoopClosedEvent / TrackingEvent /
    InputEvent as they arrive and `on_event` is called for each (sync or async callable); `finish()` waits for
    every frame to be processed. Per-frame errors (e.g. a corrupt image) are collected in `summary.errors` (raised with
    `raise_on_frame_error=True`); stream-level errors and a closed connection raise `StreamError`.
    """

    def __init__(self, url: str, session_id: str, headers: dict[str, str], *, flow: FlowControl | None = None,
                 wire: WireOptions = WireOptions(), on_event: EventCallback | None = None,
                 idle_timeout_s: float = 300.0, raise_on_frame_error: bool = False,
                 resume: Callable[[bool], Awaitable[ResumePoint]] | None = None, reconnect_s: float = 30.0) -> None:
        """`resume(with_results)` asks the server (REST) where the session stands: the stream then starts after
        its last accepted seq, and a lost connection is re-opened (for up to `reconnect_s`, then
        ServerUnreachableError) and caught up (see client.resume) instead of failing the stream."""
        self.url = url
        self.session_id = session_id
        self.headers = headers
        self.flow = flow or FlowControl()
        self.wire = wire
        self.on_event = on_event
        self.idle_timeout_s = idle_timeout_s
        self.raise_on_frame_error = raise_on_frame_error
        self.summary = StreamSummary(session_id=session_id)
        self._ws: Any = None
        self._reader: asyncio.Task | None = None
        self._outbox: deque[tuple[int | None, FrameLike]] = deque()  # (seq to re-send under, or None; frame)
        self._next_seq = 0
        self._changed = asyncio.Event()
        self._finished = asyncio.Event()
        self._failure: FlashMonoError | None = None
        self._events: asyncio.Queue[StreamEvent | None] = asyncio.Queue()
        self._started = 0.0
        self.resume = resume
        self.reconnect_s = reconnect_s
        self._reconnecting: asyncio.Task | None = None
        self._finish_sent = False
        self._closing = False
        self._result_seqs: set[int] = set()

    # -------------------------------------------------------------------------------------------- lifecycle
    async def connect(self) -> AsyncFrameStream:
        if self.resume is not None:  # a stream opened again on a session continues after its last accepted seq
            point = await self._resume_point(with_results=False)
            self._next_seq = max(self._next_seq, point.last_seq + 1)
        await self._open(open_timeout_s=30)
        self._started = time.monotonic()
        return self

    async def _resume_point(self, with_results: bool) -> ResumePoint:
        try:
            return await self.resume(with_results)
        except httpx.TransportError as err:
            raise ServerUnreachableError(f"cannot reach the server to resume the stream: {err}") from err
        except httpx.HTTPStatusError as err:
            raise error_for_status(err.response.status_code, _json_or_text(err.response)) from err

    async def _open(self, open_timeout_s: float) -> None:
        """Open the socket and start its reader (keepalive pings find a silent server within ~15 s)."""
        import websockets
        from websockets.exceptions import InvalidStatus

        try:
            self._ws = await websockets.connect(self.url, additional_headers=self.headers, max_size=2**24,
                                                open_timeout=open_timeout_s, ping_interval=5, ping_timeout=10)
        except InvalidStatus as err:
            response = err.response
            body: Any = bytes(response.body or b"").decode("utf-8", "replace")
            try:
                body = json.loads(body)
            except ValueError:
                pass
            raise error_for_status(response.status_code, body, response.reason_phrase) from err
        except (OSError, TimeoutError) as err:
            raise ServerUnreachableError(f"cannot open the stream at {self.url}: {err}") from err
        self._reader = asyncio.create_task(self._read_loop())

    async def __aenter__(self) -> AsyncFrameStream:
        return await self.connect()

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    async def close(self) -> None:
        """Close the socket (without finishing the session) and stop the reader."""
        self._closing = True
        if self._reconnecting is not None:
            self._reconnecting.cancel()
        if self._ws is not None:
            await self._ws.close()
        if self._reader is not None:
            try:
                await asyncio.wait_for(self._reader, timeout=5)
            except (TimeoutError, asyncio.CancelledError):
                self._reader.cancel()
        self._events.put_nowait(None)
        self.summary.frames_dropped = len(self.flow.dropped)
        self.summary.elapsed_s = time.monotonic() - self._started if self._started else 0.0

    # ---------------------------------------------------------------------------------------------- sending
    async def send(self, frame: FrameLike) -> None:
        """Queue `frame` and send everything the flow control allows; returns once `frame` is on the wire."""
        if self._ws is None:
            raise StreamError("the stream is not connected", code="not_connected")
        self._outbox.append((None, frame))
        await self._pump(lambda: not self._outbox)

    async def finish(self, timeout_s: float | None = None) -> StreamSummary:
        """Send what is left, tell the server no more frames will come and wait for it to process them all."""
        await self._pump(lambda: not self._outbox and not self.flow.in_flight and not self.flow.refused)
        await self._send_finish()
        wait_s = timeout_s if timeout_s is not None else self.idle_timeout_s
        while not self._finished.is_set():
            self._raise_if_failed()
            self._changed.clear()
            try:
                await asyncio.wait_for(self._changed.wait(), timeout=wait_s)
            except TimeoutError as err:
                raise StreamError(f"the server did not finish within {wait_s:.0f} s", code="timeout") from err
        await self.close()
        return self.summary

    async def _send_finish(self) -> None:
        """Send "finish"; after a lost connection the reconnect sends it again if the server did not get it."""
        self._finish_sent = True
        try:
            await self._ws.send(json.dumps({"type": "finish"}))
        except Exception as err:  # websockets raises ConnectionClosed subclasses
            if not self._may_reconnect():
                raise self._failure or StreamError(f"the stream closed while finishing: {err}", code="closed") from err

    async def ping(self) -> None:
        await self._ws.send(json.dumps({"type": "ping"}))

    async def _pump(self, done: Callable[[], bool]) -> None:
        while not done():
            self._raise_if_failed()
            if self.flow.recovery_ready():
                resends, delay = self.flow.take_resends()
                self.summary.backpressure_retries += len(resends)
                self._outbox.extendleft(reversed(resends))
                await asyncio.sleep(delay)
                continue
            if self._outbox and self.flow.can_send():
                await self._send_now(*self._outbox.popleft())
                continue
            self._changed.clear()
            try:
                await asyncio.wait_for(self._changed.wait(), timeout=self.idle_timeout_s)
            except TimeoutError as err:
                raise StreamError(f"no answer from the server for {self.idle_timeout_s:.0f} s "
                                  f"({self.flow.unsettled} frames unsettled)", code="timeout") from err

    async def _send_now(self, seq: int | None, frame: FrameLike) -> None:
        """Send `frame` under `seq` (a re-send keeps its seq: the server asks for it by number) or the next one."""
        first_send = seq is None
        if seq is None:
            seq = self._next_seq
            self._next_seq += 1
        payload = await asyncio.to_thread(encode_frame_message, frame, seq, self.wire)
        self.flow.on_sent(seq, frame)
        try:
            await self._ws.send(payload)
        except Exception as err:  # websockets raises ConnectionClosed subclasses
            if self._may_reconnect():
                return  # in flight: the reconnect re-sends it unless the server had queued it
            raise self._failure or StreamError(f"the stream closed while sending: {err}", code="closed") from err
        self.summary.frames_sent += first_send  # distinct frames; re-sends are counted in backpressure_retries

    def _raise_if_failed(self) -> None:
        if self._failure is not None:
            raise self._failure

    # ---------------------------------------------------------------------------------------------- receiving
    async def _read_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for raw in self._ws:
                await self._handle(raw)
                self._changed.set()
        except ConnectionClosed:
            pass
        except Exception as err:  # a bug in a callback or a malformed message must not hang the sender
            self._failure = self._failure or StreamError(f"stream reader failed: {err!r}", code="client_error")
        finally:
            if not self._finished.is_set() and self._failure is None and self._may_reconnect():
                if self._reconnecting is None or self._reconnecting.done():
                    self._reconnecting = asyncio.create_task(self._reconnect())
            else:
                if not self._finished.is_set() and self._failure is None:
                    close = getattr(self._ws, "close_reason", None) or getattr(self._ws, "close_code", None)
                    self._failure = StreamError(f"the server closed the stream ({close or 'no reason given'})",
                                                code="closed")
                self._events.put_nowait(None)
            self._changed.set()

    def _may_reconnect(self) -> bool:
        """A lost connection is re-opened unless the stream is closing or the server refused it for good."""
        code = getattr(self._ws, "close_code", None)
        return (self.resume is not None and self.reconnect_s > 0 and not self._closing
                and not self._finished.is_set() and self._failure is None and code not in _FINAL_CLOSE_CODES)

    async def _reconnect(self) -> None:
        """Re-open the stream and catch up with the server; ServerUnreachableError after `reconnect_s`."""
        deadline = time.monotonic() + self.reconnect_s
        delay = 0.2
        while True:
            try:
                point = await self._resume_point(with_results=True)
                if point.status in ("finishing", "finished", "failed") and self._finish_sent:
                    await self._finish_via_rest(point, deadline)
                    return
                await self._open(open_timeout_s=max(1.0, min(10.0, deadline - time.monotonic())))
                point = await self._resume_point(with_results=True)  # results up to the new socket's start
                break
            except (ServerUnreachableError, ServerError) as err:  # down, or up without Redis yet (503)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._fail(ServerUnreachableError(
                        f"lost the stream of session {self.session_id} and could not reconnect within "
                        f"{self.reconnect_s:g} s ({self.flow.unsettled} frames unsettled): {err}"))
                    return
                await asyncio.sleep(min(delay, remaining))  # the last attempt comes at the deadline
                delay = min(2.0, delay * 2)
            except FlashMonoError as err:
                self._fail(err)
                return
        self.summary.reconnects += 1
        resend, missed = reconcile(self.flow, point)
        self._outbox.extendleft(reversed(resend))
        for message in missed:
            await self._handle(json.dumps(message))
        if self._finish_sent and point.status in ("created", "streaming") and not resend:
            await self._ws.send(json.dumps({"type": "finish"}))  # the server never got it
        self._changed.set()

    async def _finish_via_rest(self, point: ResumePoint, deadline: float) -> None:
        """The connection broke after "finish": wait for the session to finish (REST), then report its results."""
        wait_until = max(deadline, time.monotonic() + self.idle_timeout_s)
        while point.status == "finishing" and time.monotonic() < wait_until:
            await asyncio.sleep(0.5)
            point = await self._resume_point(with_results=True)
        if point.status != "finished":
            self._fail(StreamError(f"the session is {point.status} after the connection was lost",
                                   code="engine_failed" if point.status == "failed" else "timeout"))
            return
        self.summary.reconnects += 1
        for seq in sorted(self.flow.in_flight):
            self.flow.on_ack(seq)
        _, missed = reconcile(self.flow, point)
        for message in missed:
            await self._handle(json.dumps(message))
        self.summary.finished_frames = len(point.poses)
        self._finished.set()
        self._events.put_nowait(None)
        self._changed.set()

    def _fail(self, error: FlashMonoError) -> None:
        self._failure = self._failure or error
        self._events.put_nowait(None)
        self._changed.set()

    async def _handle(self, raw: str | bytes) -> None:
        try:
            message = json.loads(raw)
        except ValueError:
            from protocol.codec import unpack

            message = unpack(raw) if isinstance(raw, bytes) else {}
        if not isinstance(message, dict):
            return
        parsed = parse_server_message(message)
        if isinstance(parsed, AckMessage):
            self.flow.on_ack(int(parsed.seq), parsed.queue_depth)
            self.summary.frames_acked += 1
            self.summary.max_queue_depth = max(self.summary.max_queue_depth, int(parsed.queue_depth or 0))
        elif isinstance(parsed, SkippedMessage):  # the tracker dropped it for a newer frame: its result
            self.flow.on_result(int(parsed.seq))
            self.summary.skipped.append(int(parsed.seq))
        elif isinstance(parsed, ErrorMessage):
            self._handle_error(message)
        elif isinstance(parsed, FinishedMessage):
            self.summary.finished_frames = parsed.frames
            self._finished.set()
        else:
            await self._on_event(stream_event(parsed, message))

    async def _on_event(self, event: StreamEvent | None) -> None:
        if isinstance(event, PoseEvent):
            if event.seq in self._result_seqs:
                return  # already reported (a result caught up from the trajectory after a reconnect)
            self._result_seqs.add(event.seq)
            self.flow.on_result(event.seq)
            self.summary.poses.append(event)
        elif isinstance(event, LoopClosedEvent):
            self.summary.loop_closures.append(event)
        elif isinstance(event, TrackingEvent):
            self.summary.tracking_events.append(event)
        elif isinstance(event, InputEvent):
            self.summary.input_events.append(event)
        else:
            return
        await self._publish(event)

    def _handle_error(self, message: dict[str, Any]) -> None:
        status = _REFUSAL_STATUS.get(str(message.get("code")))
        if status is not None and message.get("seq") is None:  # the server refused the stream itself
            self._failure = error_for_status(status, {"detail": message.get("message") or message.get("code")})
            return
        error = stream_error_from_frame(message)
        if error.seq is not None and error.code in ("backpressure", "unavailable"):  # not queued: re-send later
            self.flow.on_refused(error.seq)
            return
        self.summary.errors.append(message)
        if error.seq is not None:
            self.flow.on_rejected(error.seq)
            if self.raise_on_frame_error:
                self._failure = error
        else:
            self._failure = error

    async def _publish(self, event: StreamEvent | None) -> None:
        if event is None:
            return
        self._events.put_nowait(event)
        if self.on_event is not None:
            result = self.on_event(event)
            if inspect.isawaitable(result):
                await result

    async def events(self) -> AsyncIterator[StreamEvent]:
        """Live events until the stream ends (finished, failed or closed)."""
        while True:
            event = await self._events.get()
            if event is None:
                self._events.put_nowait(None)  # let other iterators end too
                return
            yield event


class AsyncFlashMonoClient:
    """Asynchronous client of a Flash-Mono gateway. `api_key` goes in the X-API-Key header."""

    def __init__(self, server_url: str = DEFAULT_SERVER, api_key: str | None = None, *, timeout_s: float = 60.0,
                 transport: httpx.AsyncBaseTransport | None = None) -> None:
        websocket_url(server_url, "")  # validates the scheme
        self.server_url = server_url.rstrip("/")
        self.api_key = api_key
        self._http = httpx.AsyncClient(base_url=self.server_url, headers=self._auth_headers(), timeout=timeout_s,
                                       transport=transport)

    def _auth_headers(self) -> dict[str, str]:
        return {"X-API-Key": self.api_key} if self.api_key else {}

    async def __aenter__(self) -> AsyncFlashMonoClient:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _call(self, call: rest.Call) -> Any:
        try:
            response = await self._http.request(call.method, call.path, **call.request_options())
        except httpx.TransportError as err:
            raise ServerUnreachableError(f"cannot reach {self.server_url}: {err}") from err
        rest.raise_for_error(response)
        return call.parse(response)

    # ------------------------------------------------------------------------------------------------ REST
    async def health(self) -> dict[str, Any]:
        return await self._call(rest.health())

    async def ready(self) -> dict[str, Any]:
        """/readyz: raises ServerError (503) while Redis or every worker is unreachable."""
        return await self._call(rest.ready())

    async def create_session(self, *, intrinsics: Any = None, preset: str | None = None, name: str | None = None,
                             device_id: str | None = None, metadata: dict[str, Any] | None = None,
                             pose_mode: str | None = None, skip_frames: bool | None = None,
                             tracking_side: int | None = None, frame_rate: float | None = None,
                             map_id: str | None = None, map_mode: str | None = None) -> Session:
        """A new session (see FlashMonoClient.create_session)."""
        return await self._call(rest.create_session(intrinsics, preset, name, device_id, metadata, pose_mode,
                                                    skip_frames, tracking_side, frame_rate, map_id, map_mode))

    async def presets(self) -> dict[str, Any]:
        """GET /v1/presets: {presets: [{name, purpose, input}], input_modes}."""
        return await self._call(rest.presets())

    async def list_sessions(self, *, status: str | None = None, device_id: str | None = None,
                            name: str | None = None, limit: int | None = None,
                            cursor: str | None = None) -> SessionPage:
        return await self._call(rest.list_sessions(status, device_id, name, limit, cursor))

    async def iter_sessions(self, *, page_size: int = 100, **filters: Any) -> AsyncIterator[Session]:
        """Every session matching `filters` (status, device_id, name), following the pagination cursor."""
        cursor = None
        while True:
            page = await self.list_sessions(limit=page_size, cursor=cursor, **filters)
            for session in page.sessions:
                yield session
            if not page.next_cursor:
                return
            cursor = page.next_cursor

    async def get_session(self, session_id: str) -> Session:
        return await self._call(rest.get_session(session_id))

    async def delete_session(self, session_id: str) -> None:
        await self._call(rest.delete_session(session_id))

    async def trajectory(self, session_id: str, which: str = "all") -> Trajectory:
        return await self._call(rest.trajectory(session_id, which))

    async def trajectory_tum(self, session_id: str, which: str = "all") -> str:
        return await self._call(rest.trajectory_tum(session_id, which))

    async def render(self, session_id: str, pose: Any, *, width: int, height: int, fx: float, fy: float,
                     cx: float, cy: float, kind: str = "color", exposure_of: int | None = None) -> bytes:
        """PNG bytes of the map seen from c2w `pose` (depth: 16-bit PNG in millimetres); colours normalised, or
        with `exposure_of` (a frame's seq) as that frame's photo shows them."""
        return await self._call(rest.render(session_id, pose, width, height, fx, fy, cx, cy, kind, exposure_of))

    async def render_array(self, session_id: str, pose: Any, *, kind: str = "color", **camera: Any) -> np.ndarray:
        """Like `render`, decoded: RGB uint8 [H, W, 3] or depth in metres float32 [H, W]."""
        return decode_png(await self.render(session_id, pose, kind=kind, **camera), kind)

    async def download_map(self, session_id: str, sh_degree: int = 0, format: str = "ply") -> bytes:
        """The session's surfel map as PLY bytes (sh_degree 3: with the 45 zero f_rest coefficients); format "spz"
        or "splat" for web viewers."""
        return await self._call(rest.map_ply(session_id, sh_degree, format))

    # ------------------------------------------------------------------------------------------------ maps
    async def create_map(self, session_id: str, name: str) -> MapInfo:
        """Save the map of a finished session this key created as a new map named `name`."""
        return await self._call(rest.create_map(session_id, name))

    async def upload_map(self, path_or_bytes: str | Path | bytes, name: str | None = None) -> MapInfo:
        """Upload a map package (a file or its bytes) as a new map; `name` defaults to the package's."""
        return await self._call(rest.upload_map(rest.package_bytes(path_or_bytes), name))

    async def list_maps(self, *, limit: int | None = None, cursor: str | None = None) -> MapPage:
        return await self._call(rest.list_maps(limit, cursor))

    async def get_map(self, map_id: str) -> MapInfo:
        """A map with every version and the sessions that built or used it."""
        return await self._call(rest.get_map(map_id))

    async def delete_map(self, map_id: str) -> None:
        await self._call(rest.delete_map(map_id))

    async def download_saved_map(self, map_id: str, format: str = "ply", *, version: int | None = None,
                                 sh_degree: int = 0) -> bytes:
        """A saved map's file: "package" or its surfels as "ply", "spz" or "splat" (see FlashMonoClient)."""
        return await self._call(rest.map_file(map_id, format, version, sh_degree))

    # ------------------------------------------------------------------------------------------- streaming
    def open_stream(self, session_id: str, *, window: int = 4, max_pending: int = 8, max_retries: int = 20,
                    wire: WireOptions = WireOptions(), on_event: EventCallback | None = None,
                    idle_timeout_s: float = 300.0, raise_on_frame_error: bool = False,
                    reconnect_s: float = 30.0) -> AsyncFrameStream:
        """A stream into `session_id` (connect with `async with`). See AsyncFrameStream and FlowControl.

        The stream starts after the session's last accepted seq, and re-opens a lost connection for up to
        `reconnect_s` seconds (0: never), catching up without loss or renumbering (client.resume)."""
        url = websocket_url(self.server_url, f"{rest.API_PREFIX}/sessions/{quote(session_id, safe='')}/stream")
        flow = FlowControl(window=window, max_pending=max_pending, max_retries=max_retries)

        def resume(with_results: bool) -> Awaitable[ResumePoint]:
            return fetch_resume_point(self._http, session_id, with_results)

        return AsyncFrameStream(url, session_id, self._auth_headers(), flow=flow, wire=wire, on_event=on_event,
                                idle_timeout_s=idle_timeout_s, raise_on_frame_error=raise_on_frame_error,
                                resume=resume, reconnect_s=reconnect_s)

    async def stream(self, session_id: str, source: Any, *, on_event: EventCallback | None = None,
                     on_sent: Callable[[StreamSummary], Any] | None = None, fps: float | None = None,
                     stride: int = 1, max_frames: int | None = None, resize: tuple[int, int] | None = None,
                     source_options: dict[str, Any] | None = None, **stream_options: Any) -> StreamSummary:
        """Stream every frame of `source` (see client.streaming.open_frames) into the session and finish it.

        fps: pace sending like a live camera (None: as fast as the flow control allows). on_sent is called with
        the running summary after each frame goes out (progress bars).
        """
        if fps is not None and fps <= 0:
            raise ValueError("fps must be positive")
        frames = await asyncio.to_thread(open_frames, source, stride=stride, max_frames=max_frames, resize=resize,
                                         **(source_options or {}))
        iterator = iter(frames)
        done = object()
        async with self.open_stream(session_id, on_event=on_event, **stream_options) as stream:
            start = time.monotonic()
            count = 0
            while True:
                frame = await asyncio.to_thread(next, iterator, done)
                if frame is done:
                    break
                if fps is not None:
                    await asyncio.sleep(max(0.0, start + count / fps - time.monotonic()))
                await stream.send(frame)
                count += 1
                if on_sent is not None:
                    on_sent(stream.summary)
            return await stream.finish()


def run_coroutine(factory: Callable[[], Awaitable[Any]]) -> Any:
    """Run a coroutine to completion from sync code, also when the caller already runs an event loop."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(factory())
    import concurrent.futures

    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        return pool.submit(lambda: asyncio.run(factory())).result()
