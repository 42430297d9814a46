"""The FastAPI gateway: `create_app(settings)`; `app` for `uvicorn service.app:app`."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from redis.asyncio.retry import Retry
from redis.backoff import NoBackoff

from protocol.presets import check_preset
from service import (
    hardening,
    routes_events,
    routes_health,
    routes_maps,
    routes_presets,
    routes_results,
    routes_sessions,
    routes_stream,
)
from service.auth import Authenticator
from service.maps import MapStore
from service.metrics import GatewayMetrics
from service.outbox_hub import OutboxHub
from service.registry import Registry
from service.settings import Settings
from service.websocket_doc import WEBSOCKET_DOC
from worker.runtime.archive import BlobStore
from worker.runtime.connection import close_async, connect_async, is_cluster_url

log = logging.getLogger(__name__)
VIEWER_DIR = Path(__file__).parent / "static" / "viewer"
API_VERSION = "0.1.0"


API_DESCRIPTION = (
    "Real-time monocular 2D Gaussian-splatting SLAM as a service. Authenticate with `X-API-Key: <key>` or "
    "`Authorization: Bearer <key>` (WebSocket also `?api_key=`).\n\n"
    "**A mobile app streaming its camera live** creates its session with `{\"skip_frames\": true, "
    "\"frame_rate\": 30, \"intrinsics\": {...}}` (the intrinsics where the platform gives them: ARKit and ARCore "
    "do) and nothing else: no preset, no tuning fields. Its frames carry `depth` where the phone has a depth "
    "sensor and `pose` where it runs ARKit/ARCore; the worker chooses the settings at the first frame from what "
    "arrives and from its machine, and the session's `settings` says what it chose and why. Recorded data (every "
    "frame must get a pose, however late) leaves `skip_frames` false.")


def create_app(settings: Settings | None = None) -> FastAPI:
    """The gateway app; connects to Redis at start-up."""
    settings = settings or Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # a bounded pool: a burst of requests waits for a connection instead of opening hundreds; on a cluster the
        # outbox hub holds one more connection per streaming session (see OutboxHub)
        connections, options = settings.redis_connections, {}
        if is_cluster_url(settings.redis_url):
            connections += settings.max_streams
            # no silent retry across a failover: a frame whose ingest broke in flight is refused as `unavailable`
            # and, re-sent, acked if it had been queued (a retry inside redis-py would answer it bad_seq)
            options["retry"] = Retry(NoBackoff(), 0)
        client = connect_async(settings.redis_url, connections, health_check_interval=30,
                               client_name="flashmono-gateway", **options)
        app.state.registry = Registry(client, BlobStore(settings.blob_dir) if settings.blob_dir else None,
                                      wait_replicas=settings.redis_wait_replicas,
                                      wait_timeout_ms=settings.redis_wait_ms)
        app.state.maps = MapStore(client)
        app.state.outbox_hub = OutboxHub(client)
        app.state.outbox_hub.start()
        try:
            yield
        finally:
            await app.state.outbox_hub.stop()
            await close_async(client)

    app = FastAPI(title="Flash-Mono", version=API_VERSION, lifespan=lifespan,
                  description=API_DESCRIPTION)
    app.state.settings = settings
    app.state.auth = Authenticator(settings)
    app.state.metrics = GatewayMetrics()
    app.state.validate_preset = check_preset
    hardening.install(app, settings.max_body_bytes, {routes_maps.router.prefix: settings.max_map_bytes})
    for module in (routes_sessions, routes_maps, routes_presets, routes_results, routes_stream, routes_events,
                   routes_health):
        app.include_router(module.router)
    if VIEWER_DIR.is_dir():
        app.mount("/viewer/static", StaticFiles(directory=VIEWER_DIR), name="viewer-static")
        app.add_api_route("/viewer", _viewer_index, include_in_schema=False)
        app.add_api_route("/viewer/capture", _capture_page, include_in_schema=False)
    app.openapi = lambda: _openapi_with_websocket(app)
    return app


async def _viewer_index():
    from fastapi.responses import FileResponse, PlainTextResponse

    index = VIEWER_DIR / "index.html"
    return FileResponse(index) if index.is_file() else PlainTextResponse("viewer not installed", status_code=404)


async def _capture_page():
    """The phone's capture page: the camera streamed to a new session (same auth as the API: the key is asked)."""
    from fastapi.responses import FileResponse, PlainTextResponse

    page = VIEWER_DIR / "capture.html"
    return FileResponse(page) if page.is_file() else PlainTextResponse("capture page not installed", status_code=404)


def _openapi_with_websocket(app: FastAPI) -> dict[str, Any]:
    """The generated schema plus the WebSocket protocol (OpenAPI has no WebSocket operations: an x- extension)."""
    if app.openapi_schema is None:
        from fastapi.openapi.utils import get_openapi

        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        schema["x-websocket"] = WEBSOCKET_DOC
        app.openapi_schema = schema
    return app.openapi_schema


def __getattr__(name: str):
    """`service.app:app` builds the app from the environment on first access (uvicorn service.app:app)."""
    if name == "app":
        global app
        app = create_app()
        return app
    raise AttributeError(name)
