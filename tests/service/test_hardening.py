"""What every response gets: JSON errors, body size limits, security headers on the viewer, the WebSocket Origin
allow-list, redacted access logs, and render/export timeouts that honour the configured value."""

from __future__ import annotations

import asyncio
import json
import logging
import time

import httpx
import pytest
import redis.asyncio as aioredis
from conftest import STREAM_KEY
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from service.app import create_app
from service.hardening import VIEWER_CSP, origin_allowed, redact, redact_access_logs
from service.redis_embedded import EmbeddedRedis
from service.registry import Registry, RequestTimeout
from service.settings import Settings


def test_oversized_bodies_get_413_json(api):
    r = api.post("/v1/sessions", json={"metadata": {"blob": "x" * (2 * 1024 * 1024)}})
    assert r.status_code == 413 and "exceeds the limit" in r.json()["detail"]
    chunked = api.post("/v1/sessions", content=(b"x" * 65536 for _ in range(40)),
                       headers={"content-type": "application/json"})
    assert chunked.status_code == 413 and chunked.headers["content-type"] == "application/json"
    assert api.post("/v1/sessions", json={"metadata": {"note": "small"}}).status_code == 201


def test_viewer_and_api_responses_carry_security_headers(api):
    for path in ("/viewer", "/viewer/static/viewer.js"):
        r = api.get(path)
        assert r.status_code == 200
        assert r.headers["content-security-policy"] == VIEWER_CSP
        assert r.headers["x-frame-options"] == "DENY" and r.headers["referrer-policy"] == "no-referrer"
        assert r.headers["x-content-type-options"] == "nosniff"
    r = api.get("/v1/sessions")
    assert r.headers["x-content-type-options"] == "nosniff" and "content-security-policy" not in r.headers
    missing = api.get("/v1/no-such-route")
    assert missing.status_code == 404 and missing.json()["detail"]


def test_websocket_origin_allow_list(api, stack):
    sid = api.post("/v1/sessions", json={}).json()["id"]
    url = f"{stack.ws_url}/v1/sessions/{sid}/stream"
    with connect(url, additional_headers={"X-API-Key": STREAM_KEY}, origin="https://evil.example") as ws:
        message = json.loads(ws.recv(timeout=10))
        assert message["code"] == "forbidden_origin" and "evil.example" in message["message"]
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)
        assert ws.close_code == 4403
    for origin in (stack.base_url, None):  # the gateway's own viewer, and clients that are not browsers
        with connect(url, additional_headers={"X-API-Key": STREAM_KEY}, origin=origin) as ws:
            ws.send(json.dumps({"type": "ping"}))
            assert json.loads(ws.recv(timeout=10)) == {"type": "pong"}
    assert origin_allowed("https://app.example", "gw:8000", frozenset({"https://app.example"}))
    assert origin_allowed("https://any.example", "gw:8000", frozenset({"*"}))
    assert not origin_allowed("https://gw:8000.evil", "gw:8000", frozenset())


def test_api_keys_are_redacted_from_access_logs(caplog):
    assert redact("GET /v1/sessions/a/stream?api_key=s3cr3t&x=1") == "GET /v1/sessions/a/stream?api_key=<redacted>&x=1"
    redact_access_logs()
    redact_access_logs()  # idempotent
    logger = logging.getLogger("uvicorn.access")
    assert sum(type(f).__name__ == "_RedactSecrets" for f in logger.filters) == 1
    caplog.set_level(logging.INFO, logger="uvicorn.error")
    with caplog.at_level(logging.INFO, logger="uvicorn.access"):
        logger.info('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5", "GET", "/viewer?session=1&api_key=TOPSECRET", "1.1",
                    200)
        logging.getLogger("uvicorn.error").info('%s - "WebSocket %s" [accepted]', "127.0.0.1:5",
                                                "/v1/sessions/1/stream?api_key=TOPSECRET")
    assert "TOPSECRET" not in caplog.text and caplog.text.count("api_key=<redacted>") == 2


def test_unhandled_errors_are_json_500():
    app = create_app(Settings(redis_url="redis://127.0.0.1:1/0"))

    @app.get("/boom")
    async def boom():
        raise RuntimeError("kaput")

    async def call() -> httpx.Response:
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.get("/boom")

    r = asyncio.run(call())
    assert r.status_code == 500 and "RuntimeError" in r.json()["detail"]


def test_request_timeout_is_the_configured_one_and_says_so():
    """No worker answers: the wait lasts the configured 5.6 s (longer than redis-py's 5 s socket timeout)."""
    with EmbeddedRedis() as server:
        async def ask() -> tuple[float, str]:
            client = aioredis.Redis.from_url(server.url)
            t0 = time.monotonic()
            try:
                await Registry(client).request("s", "render", {}, live=False, timeout_s=5.6)
            except RequestTimeout as err:
                return time.monotonic() - t0, str(err)
            finally:
                await client.aclose()
            raise AssertionError("no timeout")

        elapsed, message = asyncio.run(ask())
    assert 5.5 <= elapsed < 7.5 and "within 5.6 s" in message
