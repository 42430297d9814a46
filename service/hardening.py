"""What every response of the gateway gets, whatever the route: JSON errors (never a plain-text 500), a body size
limit, security headers (strict ones on the viewer), an Origin allow-list for WebSockets, and access logs with
API keys redacted.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import urlsplit

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import get_route_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from worker.runtime.outage import REDIS_DOWN

log = logging.getLogger(__name__)

VIEWER_DIR = Path(__file__).parent / "static" / "viewer"


def inline_import_map_hashes(directory: Path = VIEWER_DIR) -> list[str]:
    """CSP sources ('sha256-...') of the inline import maps of the viewer's pages: browsers read import maps only
    inline, and the splat renderer's modules are found through one (three, @sparkjsdev/spark)."""
    sources = set()
    for page in sorted(directory.glob("*.html")) if directory.is_dir() else []:
        for body in re.findall(r'<script type="importmap">(.*?)</script>', page.read_text(), flags=re.S):
            sources.add("'sha256-" + base64.b64encode(hashlib.sha256(body.encode()).digest()).decode() + "'")
    return sorted(sources)


# 'wasm-unsafe-eval' and blob: workers: the splat renderer (Spark) decodes and sorts splats in WebAssembly inside a
# Web Worker it starts from a blob URL. No 'unsafe-eval', no inline script but the import maps.
_SCRIPT_SOURCES = " ".join(["'self'", "'wasm-unsafe-eval'", *inline_import_map_hashes()])
VIEWER_CSP = (f"default-src 'self'; script-src {_SCRIPT_SOURCES}"
              "; worker-src 'self' blob:; style-src 'self'; img-src 'self' blob: data:; "
              "connect-src 'self'; media-src 'self' blob: mediastream:; object-src 'none'; base-uri 'none'; "
              "form-action 'none'; frame-ancestors 'none'")
_COMMON_HEADERS = [(b"x-content-type-options", b"nosniff")]
_VIEWER_HEADERS = [(b"content-security-policy", VIEWER_CSP.encode()), (b"x-frame-options", b"DENY"),
                   (b"referrer-policy", b"no-referrer"), (b"cache-control", b"no-store")]
# the vendored libraries (3.4 MB) change only with a release: cacheable for a day
_VENDOR_PREFIX = "/viewer/static/vendor/"
_VENDOR_HEADERS = [*_VIEWER_HEADERS[:-1], (b"cache-control", b"public, max-age=86400")]
_SECRET_QUERY = re.compile(r"(?i)((?:api_key|apikey|token|access_token)=)[^&\s\"']+")


def install(app: FastAPI, max_body_bytes: int, larger_bodies: Mapping[str, int] | None = None) -> None:
    """JSON error handlers and the header/body-limit middleware (`larger_bodies`: path -> its own, larger bound,
    e.g. map uploads); the access-log redaction (idempotent)."""
    for error in REDIS_DOWN:
        app.add_exception_handler(error, _storage_unavailable)
    app.add_exception_handler(Exception, _internal_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=max_body_bytes, larger_bodies=larger_bodies)
    app.add_middleware(SecurityHeadersMiddleware)
    redact_access_logs()


async def _storage_unavailable(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": f"the session store (Redis) is unreachable: {exc}; retry shortly"},
                        status_code=503, headers={"retry-after": "2"})


async def _http_error(request: Request, exc: StarletteHTTPException):
    """FastAPI's JSON error answer; a 405's `Allow` names every documented method of the path (Starlette's names
    only those of the route that matched first: POST of /v1/sessions but not GET)."""
    if exc.status_code == 405:
        methods = set(documented_methods(request.app, get_route_path(request.scope)))
        if methods:
            routed = (exc.headers or {}).get("Allow", "")
            methods |= {m.strip() for m in routed.split(",") if m.strip()}
            exc = StarletteHTTPException(405, exc.detail, headers={**(exc.headers or {}),
                                                                    "Allow": ", ".join(sorted(methods))})
    return await http_exception_handler(request, exc)


_HTTP_METHODS = frozenset({"get", "put", "post", "delete", "options", "head", "patch", "trace"})


def documented_methods(app: FastAPI, path: str) -> list[str]:
    """The methods the app's OpenAPI schema documents for `path` (templated segments match any one segment)."""
    table = getattr(app.state, "documented_methods", None)
    if table is None:
        table = app.state.documented_methods = [
            (template.strip("/").split("/"), sorted(m.upper() for m in operations if m in _HTTP_METHODS))
            for template, operations in app.openapi().get("paths", {}).items()]
    parts = path.strip("/").split("/")
    for segments, methods in table:
        if len(segments) == len(parts) and all(
                seg == part or (seg.startswith("{") and seg.endswith("}") and part)
                for seg, part in zip(segments, parts)):
            return methods
    return []


async def _internal_error(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return JSONResponse({"detail": f"internal server error ({type(exc).__name__}); it has been logged"},
                        status_code=500)


class BodyLimitMiddleware:
    """413 with a JSON body for any HTTP request body over `max_body_bytes` (declared or streamed), or over the
    bound `larger_bodies` gives its path."""

    def __init__(self, app: ASGIApp, max_body_bytes: int, larger_bodies: Mapping[str, int] | None = None) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.larger_bodies = dict(larger_bodies or {})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.larger_bodies.get(scope["path"].rstrip("/") or "/", self.max_body_bytes)
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None:  # the server delivers no more than the declared length
            if not declared.isdigit() or int(declared) > limit:
                await self._refuse(send, limit)
                return
            await self.app(scope, receive, send)
            return
        # chunked: read it here, up to the limit (the routes read their bodies whole anyway), then hand it on
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            more = message.get("more_body", False)
            if size > limit:
                await self._refuse(send, limit)
                return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if replayed:
                return await receive()
            replayed = True
            return {"type": "http.request", "body": b"".join(chunks), "more_body": False}

        await self.app(scope, replay, send)

    async def _refuse(self, send: Send, limit: int) -> None:
        body = json.dumps({"detail": f"request body exceeds the limit of {limit} bytes"}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


class SecurityHeadersMiddleware:
    """nosniff on every response; CSP, no framing, no referrer and no caching on the viewer's pages."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        viewer = _VENDOR_HEADERS if path.startswith(_VENDOR_PREFIX) else _VIEWER_HEADERS
        extra = _COMMON_HEADERS + (viewer if path.startswith("/viewer") else [])

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                message = {**message, "headers": [*message.get("headers", []),
                                                  *[(k, v) for k, v in extra if k not in present]]}
            await send(message)

        await self.app(scope, receive, with_headers)


def origin_allowed(origin: str | None, host: str | None, allowed: frozenset[str]) -> bool:
    """A WebSocket's Origin is fine when absent (not a browser), listed (or "*" listed), or the gateway's own."""
    if origin is None or "*" in allowed or origin.rstrip("/") in allowed:
        return True
    return host is not None and urlsplit(origin).netloc.lower() == host.lower()


def redact(text: str) -> str:
    """`text` with the values of api_key=/token= query parameters replaced."""
    return _SECRET_QUERY.sub(r"\1<redacted>", text)


class _RedactSecrets(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        return True


def redact_access_logs() -> None:
    """API keys in a WebSocket's ?api_key= never reach uvicorn's logs (access and error loggers)."""
    for name in ("uvicorn.access", "uvicorn.error", "uvicorn"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _RedactSecrets) for f in logger.filters):
            logger.addFilter(_RedactSecrets())
