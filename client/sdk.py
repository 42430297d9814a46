"""The synchronous Python SDK: `FlashMonoClient`.

    from client.sdk import FlashMonoClient

    with FlashMonoClient("http://localhost:8000", api_key="...") as client:
        session = client.create_session(name="walk")
        summary = client.stream(session.id, "tests/data/icl_mini", on_event=print)   # or a video, "webcam:0"
        trajectory = client.trajectory(session.id)
        png = client.render(session.id, trajectory.poses[-1].pose, width=320, height=240, fx=262.5, fy=262.5,
                            cx=159.75, cy=119.75)
        ply = client.download_map(session.id)
        saved = client.create_map(session.id, "walk")            # keep the map; start a session in it later:
        again = client.create_session(map_id=saved.id)           # map_mode "localize" (default) or "extend"

REST calls go through httpx; `stream` runs the WebSocket stream of `AsyncFlashMonoClient` on a private event
loop, calling `on_event` for each live pose / loop closure. Errors are the typed exceptions of client.errors.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from client import rest
from client.async_sdk import DEFAULT_SERVER, AsyncFlashMonoClient, EventCallback, decode_png, run_coroutine
from client.errors import (
    AuthError,
    BackpressureError,
    BadRequestError,
    ConflictError,
    FlashMonoError,
    NotFoundError,
    PermissionDeniedError,
    RateLimitError,
    ServerError,
    ServerUnreachableError,
    StreamError,
)
from client.models import (
    InputEvent,
    LoopClosedEvent,
    MapInfo,
    MapPage,
    PoseEvent,
    Session,
    SessionPage,
    StreamSummary,
    TrackingEvent,
    Trajectory,
    TrajectoryPose,
)
from client.streaming import WireOptions

__all__ = [
    "AsyncFlashMonoClient", "AuthError", "BackpressureError", "BadRequestError", "ConflictError",
    "FlashMonoClient", "FlashMonoError", "InputEvent", "LoopClosedEvent", "MapInfo", "MapPage", "NotFoundError",
    "PermissionDeniedError",
    "PoseEvent", "RateLimitError", "ServerError", "ServerUnreachableError", "Session", "SessionPage", "StreamError",
    "StreamSummary", "TrackingEvent", "Trajectory", "TrajectoryPose", "WireOptions",
]


class FlashMonoClient:
    """Synchronous client of a Flash-Mono gateway. `api_key` goes in the X-API-Key header."""

    def __init__(self, server_url: str = DEFAULT_SERVER, api_key: str | None = None, *,
                 timeout_s: float = 60.0) -> None:
        self._async_args = (server_url, api_key, timeout_s)
        self.server_url = server_url.rstrip("/")
        if not self.server_url.startswith(("http://", "https://")):
            raise ValueError(f"server URL must start with http:// or https://, got {server_url!r}")
        self.api_key = api_key
        headers = {"X-API-Key": api_key} if api_key else {}
        self._http = httpx.Client(base_url=self.server_url, headers=headers, timeout=timeout_s)

    def __enter__(self) -> FlashMonoClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _call(self, call: rest.Call) -> Any:
        try:
            response = self._http.request(call.method, call.path, **call.request_options())
        except httpx.TransportError as err:
            raise ServerUnreachableError(f"cannot reach {self.server_url}: {err}") from err
        rest.raise_for_error(response)
        return call.parse(response)

    # ------------------------------------------------------------------------------------------------ REST
    def health(self) -> dict[str, Any]:
        return self._call(rest.health())

    def ready(self) -> dict[str, Any]:
        """/readyz: raises ServerError (503) while Redis or every worker is unreachable."""
        return self._call(rest.ready())

    def create_session(self, *, intrinsics: Any = None, preset: str | None = None, name: str | None = None,
                       device_id: str | None = None, metadata: dict[str, Any] | None = None,
                       pose_mode: str | None = None, skip_frames: bool | None = None,
                       tracking_side: int | None = None, frame_rate: float | None = None,
                       map_id: str | None = None, map_mode: str | None = None) -> Session:
        """A new session; intrinsics as {fx, fy, cx, cy, width, height}, an Intrinsics or [fx, fy, cx, cy].
        pose_mode: "seeded" tracks from the images starting from the device poses frames carry, with them as priors
        (the default with depth), "prior" uses them as the odometry refined by loop closures (the default without
        depth), "fixed" keeps them exactly as sent, "ignore" tracks without them. skip_frames: True for a live camera:
        the tracker skips frames that fell behind a newer one, with a `skipped` message; False (the server's default)
        tracks every frame however late. tracking_side: track frames at most this long a side (None: as the
        server's settings choose). preset: None lets the worker choose from the input and its machine (`auto`;
        the session's `settings` says what it chose and why). A mobile app streaming its camera live sets
        skip_frames=True and frame_rate (e.g. 30), and nothing else. map_id: start in a saved map (its latest
        version), map_mode "localize" (the default) or "extend" (the session adds a version when it finishes)."""
        return self._call(rest.create_session(intrinsics, preset, name, device_id, metadata, pose_mode,
                                              skip_frames, tracking_side, frame_rate, map_id, map_mode))

    def presets(self) -> dict[str, Any]:
        """GET /v1/presets: {presets: [{name, purpose, input}], input_modes}."""
        return self._call(rest.presets())

    def list_sessions(self, *, status: str | None = None, device_id: str | None = None, name: str | None = None,
                      limit: int | None = None, cursor: str | None = None) -> SessionPage:
        return self._call(rest.list_sessions(status, device_id, name, limit, cursor))

    def iter_sessions(self, *, page_size: int = 100, **filters: Any) -> Iterator[Session]:
        """Every session matching `filters` (status, device_id, name), following the pagination cursor."""
        return _follow_cursor(lambda cursor: self.list_sessions(limit=page_size, cursor=cursor, **filters), "sessions")

    def get_session(self, session_id: str) -> Session:
        return self._call(rest.get_session(session_id))

    def delete_session(self, session_id: str) -> None:
        self._call(rest.delete_session(session_id))

    def trajectory(self, session_id: str, which: str = "all") -> Trajectory:
        return self._call(rest.trajectory(session_id, which))

    def trajectory_tum(self, session_id: str, which: str = "all") -> str:
        return self._call(rest.trajectory_tum(session_id, which))

    def render(self, session_id: str, pose: Any, *, width: int, height: int, fx: float, fy: float, cx: float,
               cy: float, kind: str = "color", exposure_of: int | None = None) -> bytes:
        """PNG bytes of the map seen from c2w `pose` (depth: 16-bit PNG in millimetres); colours normalised, or
        with `exposure_of` (a frame's seq) as that frame's photo shows them."""
        return self._call(rest.render(session_id, pose, width, height, fx, fy, cx, cy, kind, exposure_of))

    def render_array(self, session_id: str, pose: Any, *, kind: str = "color", **camera: Any) -> np.ndarray:
        """Like `render`, decoded: RGB uint8 [H, W, 3] or depth in metres float32 [H, W]."""
        return decode_png(self.render(session_id, pose, kind=kind, **camera), kind)

    def download_map(self, session_id: str, sh_degree: int = 0, format: str = "ply") -> bytes:
        """The session's surfel map as PLY bytes: f_dc colour only (68 bytes a surfel); sh_degree=3 adds the 45 zero
        f_rest coefficients fixed-record 3DGS readers expect (248 bytes a surfel). format="spz" (Niantic SPZ v3)
        or "splat" (antimatter15, 32 bytes a surfel) give what web splat viewers read."""
        return self._call(rest.map_ply(session_id, sh_degree, format))

    # ------------------------------------------------------------------------------------------------ maps
    def create_map(self, session_id: str, name: str) -> MapInfo:
        """Save the map of a finished session this key created as a new map named `name`."""
        return self._call(rest.create_map(session_id, name))

    def upload_map(self, path_or_bytes: str | Path | bytes, name: str | None = None) -> MapInfo:
        """Upload a map package (a file or its bytes, as `download_saved_map(format="package")` gives) as a new map;
        `name` defaults to the package's."""
        return self._call(rest.upload_map(rest.package_bytes(path_or_bytes), name))

    def list_maps(self, *, limit: int | None = None, cursor: str | None = None) -> MapPage:
        return self._call(rest.list_maps(limit, cursor))

    def iter_maps(self, *, page_size: int = 100) -> Iterator[MapInfo]:
        """Every map this key may read, newest first, following the pagination cursor."""
        return _follow_cursor(lambda cursor: self.list_maps(limit=page_size, cursor=cursor), "maps")

    def get_map(self, map_id: str) -> MapInfo:
        """A map with every version and the sessions that built or used it."""
        return self._call(rest.get_map(map_id))

    def delete_map(self, map_id: str) -> None:
        self._call(rest.delete_map(map_id))

    def download_saved_map(self, map_id: str, format: str = "ply", *, version: int | None = None,
                           sh_degree: int = 0) -> bytes:
        """A saved map's file: "package" (to upload elsewhere) or its surfels as "ply", "spz" or "splat"; the latest
        version unless `version` is given. (`download_map` downloads a session's map.)"""
        return self._call(rest.map_file(map_id, format, version, sh_degree))

    # ------------------------------------------------------------------------------------------- streaming
    def stream(self, session_id: str, source: Any, *, on_event: EventCallback | None = None,
               on_sent: Callable[[StreamSummary], Any] | None = None, **options: Any) -> StreamSummary:
        """Stream `source` (video, image folder, dataset path or URI, "webcam:N", or Frames) and finish.

        Blocks until the server has processed every frame. on_event gets each PoseEvent / LoopClosedEvent /
        TrackingEvent / InputEvent live.
        Options: fps, stride, max_frames, resize, source_options, window, max_pending, max_retries, wire,
        idle_timeout_s, raise_on_frame_error (see AsyncFlashMonoClient.stream / open_stream).
        """

        async def run() -> StreamSummary:
            async with AsyncFlashMonoClient(*self._async_args[:2], timeout_s=self._async_args[2]) as client:
                return await client.stream(session_id, source, on_event=on_event, on_sent=on_sent, **options)

        return run_coroutine(run)


def _follow_cursor(fetch: Callable[[str | None], Any], items: str) -> Iterator[Any]:
    """The `items` of every page `fetch(cursor)` gives (a SessionPage or a MapPage), following `next_cursor`."""
    cursor = None
    while True:
        page = fetch(cursor)
        yield from getattr(page, items)
        if not page.next_cursor:
            return
        cursor = page.next_cursor
