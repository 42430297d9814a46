"""The FastAPI gateway: `create_app(settings)`; `app` for `uvicorn service.app:app`."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import redis.asyncio as aioredis
from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from service import (
    hardening,
    routes_events,
    routes_health,
    routes_presets,
    routes_results,
    routes_sessions,
    routes_stream,
)
from service.auth import Authenticator
from service.metrics import GatewayMetrics
from service.outbox_hub import OutboxHub
from service.registry import Registry
from service.settings import Settings
from service.websocket_doc import WEBSOCKET_DOC
from worker.runtime.archive import BlobStore

log = logging.getLogger(__name__)
VIEWER_DIR = Path(__file__).parent / "static" / "viewer"
API_VERSION = "0.1.0"


def _validate_preset(name: str) -> None:
    """Raise ValueError unless `name` is a preset of the engine (worker.config is light: no torch)."""
    from worker.config import PRESETS

    if name not in PRESETS:
        raise ValueError(f"choose one of {sorted(PRESETS)}")


def create_app(settings: Settings | None = None) -> FastAPI:
    """The gateway app; connects to Redis at start-up."""
    settings = settings or Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # a bounded pool: a burst of requests waits for a connection instead of opening hundreds
        pool = aioredis.BlockingConnectionPool.from_url(settings.redis_url, max_connections=settings.redis_connections,
                                                        timeout=10, health_check_interval=30,
                                                        client_name="flashmono-gateway")
        client = aioredis.Redis(connection_pool=pool)
        app.state.registry = Registry(client, BlobStore(settings.blob_dir) if settings.blob_dir else None)
        app.state.outbox_hub = OutboxHub(client)
        app.state.outbox_hub.start()
        try:
            yield
        finally:
            await app.state.outbox_hub.stop()
            await client.aclose()
            await pool.aclose()

    app = FastAPI(title="Flash-Mono", version=API_VERSION, lifespan=lifespan,
                  description="Real-time monocular 2D Gaussian-splatting SLAM as a service. Authenticate with "
                              "`X-API-Key: <key>` or `Authorization: Bearer <key>` (WebSocket also `?api_key=`).")
    app.state.settings = settings
    app.state.auth = Authenticator(settings)
    app.state.metrics = GatewayMetrics()
    app.state.validate_preset = _validate_preset
    hardening.install(app, settings.max_body_bytes)
    for module in (routes_sessions, routes_presets, routes_results, routes_stream, routes_events, routes_health):
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
