"""The worker process's settings: one model, each field's default, bounds and meaning written here once.

A field `lease_ttl_ms` is read from the environment as FLASHMONO_LEASE_TTL_MS and from the command line as
`--lease-ttl-ms` (a flag overrides the environment, which overrides the default); REDIS_URL keeps its unprefixed
name. `python -m worker.runtime.main --help` lists them all; `python -m worker.runtime.settings` prints the table in
the README (gateway and worker).

The runtime receives one section of them, `WorkerSettings.runtime` (a `RuntimeConfig`): how sessions are run.
"""

from __future__ import annotations

import sys
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from protocol.settings_model import markdown_table
from worker.runtime.engine import ENGINE_KINDS
from worker.runtime.frames import DEFAULT_MAX_SIDE

ENV_PREFIX = "FLASHMONO_"
EngineKind = Literal[ENGINE_KINDS]  # type: ignore[valid-type]
LogLevel = Literal["CRITICAL", "ERROR", "WARNING", "INFO", "DEBUG"]


class RuntimeConfig(BaseModel):
    """How a worker runs sessions: the section of the worker's settings that `Worker` and `SessionRunner` get."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    engine: EngineKind = Field("slam", description="session engine (passthrough only measures the service itself)")
    lease_ttl_ms: int = Field(2_500, ge=1, description="a session's lease: a dead worker's sessions resume on "
                                                        "another within it")
    snapshot_every: int = Field(5, ge=1, description="keyframes between a session's snapshots")
    snapshot_every_s: float = Field(
        1.0, ge=0, description="also snapshot this often (seconds; 0: by keyframes only): bounds a takeover's "
                               "replay, which starts at the newest snapshot, also for a still camera (no keyframes)")
    max_sessions: int = Field(16, ge=1, description="sessions one worker runs at once")
    max_frame_side: int = Field(DEFAULT_MAX_SIDE, ge=32, description="frames are downscaled to this longest side "
                                                                      "(and to the session's resolution) on decode")
    tracking_side: int = Field(0, ge=0, description="sessions that name no tracking resolution track frames at most "
                                                     "this long a side (0: as their settings choose: live streams "
                                                     "over 320 px at 320, others as they come)")
    checkpoint: str = Field("", description="trained frontend weights (safetensors, e.g. from `flashmono "
                                             "convert-cut3r`); with a CUDA GPU, sessions that name no preset get "
                                             "the paper's settings")
    max_frame_attempts: int = Field(2, ge=1, description="workers that may die processing one frame before it is "
                                                          "quarantined (its session failed)")
    memory_budget_mb: int = Field(0, ge=0, description="take no new session while this process's resident memory, "
                                                        "its sessions' mapping processes included, is above it (0: no "
                                                        "limit)")
    idle_timeout_s: float = Field(600.0, ge=0, description="a session without frames this long is abandoned and "
                                                            "its slot freed (0: never)")
    transient_ttl_s: float = Field(3600.0, ge=1, description="an ended session's frames, messages and requests "
                                                              "expire after this (clients still read the last "
                                                              "messages)")
    retention_s: float = Field(0.0, ge=0, description="an ended session's record, trajectory and map expire after "
                                                       "this (0: kept)")
    blob_dir: str = Field("", description="blob store (a directory) finished sessions move to, map and trajectory "
                                          "included (empty: none)")
    archive_after_s: float = Field(3600.0, ge=0, description="finished sessions move to the blob store this long "
                                                              "after finishing")
    # Live tracking: newest first wins, but at most `max_consecutive_skips` in a row (tracking keeps its continuity)
    # and after the first none that arrived more than `max_skipped_span_ms` after the last tracked frame: the motion
    # across a gap grows with its time, not its frames (30 frames/s: five in a row; a 10 frames/s drive or a 5
    # frames/s browser: one, so a worker behind the camera still sheds half its frames).
    skip_after_ms: float = Field(100.0, ge=0, description="live tracking: a frame that waited longer than this "
                                                           "while a newer frame is waiting is skipped with a "
                                                           "`skipped` message (newest first wins; 0: never skip)")
    max_consecutive_skips: int = Field(5, ge=0, description="frames skipped in a row at most (tracking keeps its "
                                                             "continuity)")
    max_skipped_span_ms: float = Field(170.0, ge=0, description="after the first, no frame in a row is skipped that "
                                                                 "arrived more than this after the last tracked "
                                                                 "frame (at 10 frames/s: one in a row)")
    live_stats_every_s: float = Field(0.5, gt=0, description="how often a session's record gets the engine's live "
                                                              "figures")
    block_ms: int = Field(500, ge=1, description="how long one read of the worker's streams waits for entries")
    outbox_maxlen: int = Field(5000, ge=1, description="messages kept in a session's outbound stream (about)")


class ProcessOptions(BaseModel):
    """The worker process's own options (not the runtime's)."""

    redis_url: str = Field("", validation_alias="REDIS_URL",
                           description="the Redis to serve (required; `redis+cluster://host:port,...` for a cluster)")
    worker_id: str = Field("", description="this worker's name in leases and logs (empty: host-pid-random)")
    torch_threads: int = Field(0, ge=0, description="torch intra-op threads (0: torch's default)")
    switch_interval_ms: float = Field(1.0, gt=0, description="the interpreter's thread switch interval: how long the "
                                                              "tracking thread may wait for the GIL while a mapping "
                                                              "or loop thread runs Python (Python's default is 5)")
    log_level: LogLevel = Field("INFO", description="log level")

    @field_validator("log_level", mode="before")
    @classmethod
    def _upper(cls, value: Any) -> Any:
        return value.upper() if isinstance(value, str) else value


class WorkerSettings(RuntimeConfig, ProcessOptions, BaseSettings):
    """Everything a worker process is configured with: its own options and the runtime's section."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_ignore_empty=True, frozen=True, extra="forbid",
                                      validate_by_name=True, validate_by_alias=True)

    @property
    def runtime(self) -> RuntimeConfig:
        """The section the runtime gets."""
        return RuntimeConfig(**{name: getattr(self, name) for name in RuntimeConfig.model_fields})


README_BEGIN = "<!-- settings table: generated by `python -m worker.runtime.settings --readme README.md` -->"
README_END = "<!-- end of settings table -->"


def readme_tables() -> str:
    from service.settings import Settings

    return (f"{README_BEGIN}\n\n**Gateway** (`service.settings.Settings`):\n\n{markdown_table(Settings, flags=False)}"
            f"\n\n**Worker** (`worker.runtime.settings.WorkerSettings`; `python -m worker.runtime.main --help`):\n\n"
            f"{markdown_table(WorkerSettings)}\n\n{README_END}")


def _main(argv: list[str]) -> int:
    if argv[:1] == ["--readme"] and len(argv) == 2:
        path = argv[1]
        with open(path) as f:
            text = f.read()
        start, end = text.index(README_BEGIN), text.index(README_END) + len(README_END)
        with open(path, "w") as f:
            f.write(text[:start] + readme_tables() + text[end:])
        return 0
    print(readme_tables())
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
