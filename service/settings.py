"""Gateway configuration from the environment (read once at app creation)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from protocol.limits import DEFAULT_MAX_QUEUE, MAX_FRAME_BYTES, MAX_RENDER_PIXELS

SCOPES = ("stream", "read", "admin")


@dataclass(frozen=True)
class Settings:
    """REDIS_URL; FLASHMONO_API_KEYS ("key1=stream,read;key2=admin") or FLASHMONO_API_KEYS_FILE (JSON
    {key: [scopes]}); FLASHMONO_MAX_QUEUE (frames queued per session, 64); FLASHMONO_MAX_FRAME_BYTES (8 MiB);
    FLASHMONO_REQUEST_TIMEOUT_S (render/export reply timeout, 60); FLASHMONO_MAX_RENDER_PIXELS (4096*4096);
    FLASHMONO_MAX_BODY_BYTES (HTTP request bodies, 1 MiB); FLASHMONO_ALLOWED_ORIGINS (comma-separated origins a
    browser may open the WebSocket from besides the gateway's own, "*" for any); FLASHMONO_MAX_STREAMS (open
    WebSockets per gateway process, 2000); FLASHMONO_REDIS_CONNECTIONS (the gateway's Redis connection pool, 64);
    FLASHMONO_MAX_LIVE_SESSIONS (live sessions per API key, 100; 0: no limit); FLASHMONO_ABANDONED_GRACE_S (how long
    a session abandoned for want of frames can still be resumed by opening its stream, 3600); FLASHMONO_BLOB_DIR (the
    blob store finished sessions are archived to by the workers, read here for their trajectories);
    FLASHMONO_REDIS_WAIT_REPLICAS (0: a frame is acked once its Redis primary has it; N: once N replicas have it
    too, so a primary that fails over loses no acked frame) and FLASHMONO_REDIS_WAIT_MS (100: how long to wait for
    them; a frame still unconfirmed then is acked all the same and logged)."""

    redis_url: str = "redis://127.0.0.1:6379/0"
    api_keys: dict[str, frozenset[str]] = field(default_factory=dict)
    max_queue: int = DEFAULT_MAX_QUEUE
    max_frame_bytes: int = MAX_FRAME_BYTES
    request_timeout_s: float = 60.0
    max_render_pixels: int = MAX_RENDER_PIXELS
    max_body_bytes: int = 1024 * 1024
    allowed_origins: frozenset[str] = frozenset()
    max_streams: int = 2000
    redis_connections: int = 64
    max_live_sessions: int = 100
    abandoned_grace_s: float = 3600.0
    blob_dir: str = ""
    redis_wait_replicas: int = 0
    redis_wait_ms: int = 100

    @property
    def auth_enabled(self) -> bool:
        return bool(self.api_keys)

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None) -> Settings:
        env = os.environ if environ is None else environ
        keys = parse_api_keys(env.get("FLASHMONO_API_KEYS", ""))
        if env.get("FLASHMONO_API_KEYS_FILE"):
            keys.update(load_api_keys_file(Path(env["FLASHMONO_API_KEYS_FILE"])))
        settings = cls(
            redis_url=env.get("REDIS_URL") or cls.redis_url,
            api_keys=keys,
            max_queue=int(env.get("FLASHMONO_MAX_QUEUE", cls.max_queue)),
            max_frame_bytes=int(env.get("FLASHMONO_MAX_FRAME_BYTES", cls.max_frame_bytes)),
            request_timeout_s=float(env.get("FLASHMONO_REQUEST_TIMEOUT_S", cls.request_timeout_s)),
            max_render_pixels=int(env.get("FLASHMONO_MAX_RENDER_PIXELS", cls.max_render_pixels)),
            max_body_bytes=int(env.get("FLASHMONO_MAX_BODY_BYTES", cls.max_body_bytes)),
            max_streams=int(env.get("FLASHMONO_MAX_STREAMS", cls.max_streams)),
            redis_connections=int(env.get("FLASHMONO_REDIS_CONNECTIONS", cls.redis_connections)),
            max_live_sessions=int(env.get("FLASHMONO_MAX_LIVE_SESSIONS", cls.max_live_sessions)),
            abandoned_grace_s=float(env.get("FLASHMONO_ABANDONED_GRACE_S", cls.abandoned_grace_s)),
            blob_dir=env.get("FLASHMONO_BLOB_DIR", ""),
            redis_wait_replicas=int(env.get("FLASHMONO_REDIS_WAIT_REPLICAS", cls.redis_wait_replicas)),
            redis_wait_ms=int(env.get("FLASHMONO_REDIS_WAIT_MS", cls.redis_wait_ms)),
            allowed_origins=frozenset(o.strip().rstrip("/") for o in env.get("FLASHMONO_ALLOWED_ORIGINS", "").split(",")
                                      if o.strip()),
        )
        if settings.max_queue < 1 or settings.max_frame_bytes < 1024 or settings.max_body_bytes < 1024:
            raise ValueError("FLASHMONO_MAX_QUEUE must be >= 1, FLASHMONO_MAX_FRAME_BYTES and FLASHMONO_MAX_BODY_BYTES "
                             ">= 1024")
        if settings.redis_wait_replicas < 0 or settings.redis_wait_ms < 1:
            raise ValueError("FLASHMONO_REDIS_WAIT_REPLICAS must be >= 0 and FLASHMONO_REDIS_WAIT_MS >= 1")
        if settings.request_timeout_s <= 0:
            raise ValueError("FLASHMONO_REQUEST_TIMEOUT_S must be positive")
        if settings.max_streams < 1 or settings.redis_connections < 4 or settings.max_live_sessions < 0:
            raise ValueError("FLASHMONO_MAX_STREAMS must be >= 1 and FLASHMONO_REDIS_CONNECTIONS >= 4")
        return settings


def parse_api_keys(text: str) -> dict[str, frozenset[str]]:
    """{key: scopes} from "key1=stream,read;key2=admin"."""
    keys: dict[str, frozenset[str]] = {}
    for item in filter(None, (part.strip() for part in text.split(";"))):
        key, sep, scopes = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"FLASHMONO_API_KEYS entry {item!r} is not key=scope,scope")
        keys[key.strip()] = _checked_scopes([s.strip() for s in scopes.split(",") if s.strip()])
    return keys


def load_api_keys_file(path: Path) -> dict[str, frozenset[str]]:
    """{key: scopes} from a JSON file {key: [scopes]}."""
    data = json.loads(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object {{key: [scopes]}}")
    return {str(key): _checked_scopes(list(scopes)) for key, scopes in data.items()}


def _checked_scopes(scopes: list[str]) -> frozenset[str]:
    unknown = set(scopes) - set(SCOPES)
    if unknown or not scopes:
        raise ValueError(f"API key scopes must be a non-empty subset of {SCOPES}, got {scopes}")
    return frozenset(scopes)
