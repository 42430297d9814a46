"""A real local deployment for the service tests: embedded redis-server, uvicorn gateway, worker processes."""

from __future__ import annotations

import httpx
import pytest

from service.launcher import LocalStack

STREAM_KEY, OTHER_STREAM_KEY, READ_KEY, ADMIN_KEY = "k-stream", "k-stream-2", "k-read", "k-admin"
API_KEYS = f"{STREAM_KEY}=stream;{OTHER_STREAM_KEY}=stream;{READ_KEY}=read;{ADMIN_KEY}=admin"
MAX_FRAME_BYTES = 256 * 1024
FAST_WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LEASE_TTL_MS": "4000",
                   "FLASHMONO_SNAPSHOT_EVERY": "2", "FLASHMONO_LOG_LEVEL": "WARNING"}


@pytest.fixture(scope="session")
def stack():
    """Gateway with API keys + one worker running the passthrough engine (the runtime, not the engine, is tested)."""
    gateway_env = {"FLASHMONO_API_KEYS": API_KEYS, "FLASHMONO_MAX_FRAME_BYTES": str(MAX_FRAME_BYTES),
                   "FLASHMONO_REQUEST_TIMEOUT_S": "20"}
    with LocalStack(workers=1, gateway_env=gateway_env, worker_env=FAST_WORKER_ENV) as local:
        yield local


def client_for(stack: LocalStack, key: str | None = STREAM_KEY) -> httpx.Client:
    headers = {"X-API-Key": key} if key else {}
    return httpx.Client(base_url=stack.base_url, headers=headers, timeout=30)


@pytest.fixture
def api(stack) -> httpx.Client:
    with client_for(stack) as client:
        yield client


@pytest.fixture
def admin(stack) -> httpx.Client:
    with client_for(stack, ADMIN_KEY) as client:
        yield client
