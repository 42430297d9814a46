"""Gateway configuration from the environment (read once at app creation): one settings model."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, NoDecode, SettingsConfigDict
from pydantic_settings.sources.utils import parse_env_vars

from protocol.limits import DEFAULT_MAX_QUEUE, MAX_FRAME_BYTES, MAX_MAP_PACKAGE_BYTES, MAX_RENDER_PIXELS
from protocol.settings_model import explain

SCOPES = ("stream", "read", "admin")


class Settings(BaseSettings):
    """The gateway's settings: a field `max_queue` is read from FLASHMONO_MAX_QUEUE (REDIS_URL keeps its name).

    Each default, bound and meaning is written here once; the README's table is generated from it
    (`python -m worker.runtime.settings`). `Settings(...)` reads the environment for what it is not given;
    `Settings.from_env(environ)` reads only `environ` and names the variable of a bad value."""

    model_config = SettingsConfigDict(env_prefix="FLASHMONO_", env_ignore_empty=True, frozen=True, extra="forbid",
                                      validate_by_name=True, validate_by_alias=True)

    redis_url: str = Field("redis://127.0.0.1:6379/0", validation_alias="REDIS_URL",
                           description="the Redis the gateway and the workers share (`redis+cluster://host:port,...` "
                                       "for a cluster)")
    api_keys: Annotated[dict[str, frozenset[str]], NoDecode] = Field(
        default_factory=dict, repr=False,
        description='API keys and their scopes, "key1=stream,read;key2=admin" (scopes: stream, read, admin; none: '
                    'no authentication)')
    api_keys_file: Path | None = Field(None, description="more API keys: a JSON file {key: [scopes]}")
    max_queue: int = Field(DEFAULT_MAX_QUEUE, ge=1, description="frames queued per session before `backpressure`")
    max_frame_bytes: int = Field(MAX_FRAME_BYTES, ge=1024, description="bound of one binary frame message")
    request_timeout_s: float = Field(60.0, gt=0, description="how long a render or export waits for its worker's "
                                                              "reply")
    max_render_pixels: int = Field(MAX_RENDER_PIXELS, ge=1, description="bound of width x height of one render")
    max_body_bytes: int = Field(1024 * 1024, ge=1024, description="bound of one HTTP request body")
    max_map_bytes: int = Field(MAX_MAP_PACKAGE_BYTES, ge=1024, description="bound of one map package: the body of "
                                                                            "an upload (POST /v1/maps), and a map "
                                                                            "made from a session")
    allowed_origins: Annotated[frozenset[str], NoDecode] = Field(
        frozenset(), description="comma-separated origins a browser may open the WebSockets from besides the "
                                 "gateway's own (`*`: any)")
    max_streams: int = Field(2000, ge=1, description="open WebSockets per gateway process")
    redis_connections: int = Field(64, ge=4, description="the gateway's Redis connection pool")
    max_live_sessions: int = Field(100, ge=0, description="live sessions per API key (0: no limit)")
    abandoned_grace_s: float = Field(3600.0, ge=0, description="how long a session abandoned for want of frames "
                                                                "can still be resumed by opening its stream")
    blob_dir: str = Field("", description="the blob store the workers archive finished sessions to, read here for "
                                          "their trajectories (empty: none)")
    redis_wait_replicas: int = Field(0, ge=0, description="0: a frame is acked once its Redis primary has it; N: "
                                                           "once N replicas have it too, so a primary that fails "
                                                           "over loses no acked frame")
    redis_wait_ms: int = Field(100, ge=1, description="how long to wait for those replicas; a frame still "
                                                       "unconfirmed then is acked all the same and logged")

    @property
    def auth_enabled(self) -> bool:
        return bool(self.api_keys)

    @field_validator("api_keys", mode="before")
    @classmethod
    def _parse_keys(cls, value: Any) -> Any:
        return parse_api_keys(value) if isinstance(value, str) else value

    @field_validator("allowed_origins", mode="before")
    @classmethod
    def _parse_origins(cls, value: Any) -> Any:
        items = value.split(",") if isinstance(value, str) else value
        return frozenset(o.strip().rstrip("/") for o in items if o.strip())

    @model_validator(mode="after")
    def _load_keys_file(self) -> Settings:
        if self.api_keys_file is not None:  # the file's keys join those of FLASHMONO_API_KEYS
            try:
                keys = load_api_keys_file(self.api_keys_file)
            except (OSError, ValueError) as err:
                raise ValueError(f"FLASHMONO_API_KEYS_FILE: {err}") from err
            object.__setattr__(self, "api_keys", {**self.api_keys, **keys})
        return self

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Settings:
        """The settings from `environ` (default: the process's environment) alone; ValueError names a bad one."""
        try:
            if environ is None:
                return cls()
            return cls(_build_sources=((_Environ(cls, environ),), {}))
        except ValidationError as err:
            raise ValueError(explain(err, cls)) from None


class _Environ(EnvSettingsSource):
    """The environment source of `Settings`, over a given mapping instead of os.environ."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str]) -> None:
        self._environ = environ
        super().__init__(settings_cls)

    def _load_env_vars(self) -> Mapping[str, str | None]:
        return parse_env_vars(self._environ, self.case_sensitive, self.env_ignore_empty, self.env_parse_none_str)


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
