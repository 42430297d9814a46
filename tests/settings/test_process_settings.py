"""One settings model per process: the worker's (worker.runtime.settings.WorkerSettings, flags generated from it) and
the gateway's (service.settings.Settings); every FLASHMONO_* variable the two read is a field of one of them."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from protocol.settings_model import default_text, env_name, flag, parse_settings
from service.settings import Settings
from worker.runtime.main import build_parser, main
from worker.runtime.settings import RuntimeConfig, WorkerSettings, readme_tables

ROOT = Path(__file__).resolve().parents[2]

# The flags and variables workers were started with before the model (tests/live_stack.py, `flashmono serve`,
# docker/compose.yaml, deployments): each must keep working under its name.
LEGACY_FLAGS = {
    "--redis-url", "--worker-id", "--engine", "--lease-ttl-ms", "--snapshot-every", "--snapshot-every-s",
    "--max-sessions", "--max-frame-side", "--max-frame-attempts", "--memory-budget-mb", "--idle-timeout-s",
    "--transient-ttl-s", "--retention-s", "--blob-dir", "--archive-after-s", "--skip-after-ms",
    "--max-consecutive-skips", "--max-skipped-span-ms", "--tracking-side", "--checkpoint", "--switch-interval-ms",
    "--torch-threads", "--log-level",
}
LEGACY_WORKER_ENV = {"REDIS_URL"} | {"FLASHMONO_" + f[2:].replace("-", "_").upper() for f in LEGACY_FLAGS
                                      if f != "--redis-url"}
LEGACY_GATEWAY_ENV = {
    "REDIS_URL", "FLASHMONO_API_KEYS", "FLASHMONO_API_KEYS_FILE", "FLASHMONO_MAX_QUEUE", "FLASHMONO_MAX_FRAME_BYTES",
    "FLASHMONO_REQUEST_TIMEOUT_S", "FLASHMONO_MAX_RENDER_PIXELS", "FLASHMONO_MAX_BODY_BYTES",
    "FLASHMONO_ALLOWED_ORIGINS", "FLASHMONO_MAX_STREAMS", "FLASHMONO_REDIS_CONNECTIONS", "FLASHMONO_MAX_LIVE_SESSIONS",
    "FLASHMONO_ABANDONED_GRACE_S", "FLASHMONO_BLOB_DIR", "FLASHMONO_REDIS_WAIT_REPLICAS", "FLASHMONO_REDIS_WAIT_MS",
}
# FLASHMONO_* names in worker/runtime and service that are no setting of either process, each with its reason.
NOT_SETTINGS = {
    "FLASHMONO_FAILPOINTS": "fault injection for the crash tests (worker/runtime/failpoints.py), read at import",
    "FLASHMONO_PASSTHROUGH_DELAY_MS": "test-only: the passthrough engine's simulated compute per frame",
    "FLASHMONO_PASSTHROUGH_FINISH_MS": "test-only: the passthrough engine's simulated final refinement",
}


def _env_names(model) -> set[str]:
    return {env_name(model, name) for name in model.model_fields}


@pytest.fixture
def clean_env(monkeypatch):
    for name in list(os.environ):
        if name.startswith("FLASHMONO_") or name == "REDIS_URL":
            monkeypatch.delenv(name)
    return monkeypatch


def test_every_worker_flag_is_a_field_and_every_field_a_flag():
    shown = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", build_parser().format_help())) - {"--help"}
    fields = {flag(name) for name in WorkerSettings.model_fields}
    assert shown == fields
    assert LEGACY_FLAGS <= shown, sorted(LEGACY_FLAGS - shown)
    assert LEGACY_WORKER_ENV <= _env_names(WorkerSettings), sorted(LEGACY_WORKER_ENV - _env_names(WorkerSettings))
    assert LEGACY_GATEWAY_ENV <= _env_names(Settings), sorted(LEGACY_GATEWAY_ENV - _env_names(Settings))
    help_text = " ".join(build_parser().format_help().split())
    for name in WorkerSettings.model_fields:  # each option's help names its variable and default, from the model
        assert f"[{env_name(WorkerSettings, name)}; default: {default_text(WorkerSettings, name)}]" in help_text


def test_the_runtime_gets_its_section_defined_once():
    assert set(RuntimeConfig.model_fields) <= set(WorkerSettings.model_fields)
    for name, field in RuntimeConfig.model_fields.items():
        assert WorkerSettings.model_fields[name].default == field.default, name
    settings = WorkerSettings(redis_url="redis://x", lease_ttl_ms=300, engine="passthrough")
    runtime = settings.runtime
    assert type(runtime) is RuntimeConfig and runtime.lease_ttl_ms == 300 and runtime.engine == "passthrough"
    assert runtime.model_dump() == settings.model_dump(include=set(RuntimeConfig.model_fields))


def test_worker_flag_overrides_env_overrides_default(clean_env):
    default = WorkerSettings.model_fields["lease_ttl_ms"].default
    assert parse_settings(WorkerSettings, []).lease_ttl_ms == default
    clean_env.setenv("FLASHMONO_LEASE_TTL_MS", str(default + 1))
    clean_env.setenv("FLASHMONO_ENGINE", "passthrough")
    clean_env.setenv("REDIS_URL", "redis://env:1/0")
    clean_env.setenv("FLASHMONO_SNAPSHOT_EVERY_S", "0")
    from_env = parse_settings(WorkerSettings, [])
    assert (from_env.lease_ttl_ms, from_env.engine, from_env.redis_url, from_env.snapshot_every_s) == \
        (default + 1, "passthrough", "redis://env:1/0", 0.0)
    given = parse_settings(WorkerSettings, ["--lease-ttl-ms", str(default + 2), "--engine", "slam",
                                            "--redis-url", "redis://flag:1/0"])
    assert (given.lease_ttl_ms, given.engine, given.redis_url, given.snapshot_every_s) == \
        (default + 2, "slam", "redis://flag:1/0", 0.0)
    clean_env.setenv("FLASHMONO_MAX_SESSIONS", "0")  # a bad variable a flag overrides is no error
    assert parse_settings(WorkerSettings, ["--max-sessions", "3"]).max_sessions == 3


def test_gateway_init_overrides_env_overrides_default(clean_env):
    assert Settings().max_queue == Settings.model_fields["max_queue"].default
    clean_env.setenv("FLASHMONO_MAX_QUEUE", "7")
    clean_env.setenv("REDIS_URL", "redis://env:1/0")
    assert (Settings().max_queue, Settings().redis_url) == (7, "redis://env:1/0")
    assert Settings(max_queue=5, redis_url="redis://given:1/0").max_queue == 5
    assert Settings.from_env({"FLASHMONO_MAX_QUEUE": "9"}).max_queue == 9  # the mapping alone
    assert Settings.from_env({}).redis_url == Settings.model_fields["redis_url"].default


@pytest.mark.parametrize(("argv", "env", "named"), [
    (["--lease-ttl-ms", "0"], {}, "--lease-ttl-ms"),
    (["--engine", "fast"], {}, "--engine"),
    (["--max-frame-side", "big"], {}, "--max-frame-side"),
    ([], {"FLASHMONO_MAX_SESSIONS": "0"}, "FLASHMONO_MAX_SESSIONS"),
    ([], {"FLASHMONO_SWITCH_INTERVAL_MS": "0"}, "FLASHMONO_SWITCH_INTERVAL_MS"),
    ([], {"FLASHMONO_TRANSIENT_TTL_S": "0.5"}, "FLASHMONO_TRANSIENT_TTL_S"),
])
def test_a_bad_worker_value_exits_2_naming_it(clean_env, capsys, argv, env, named):
    for key, value in env.items():
        clean_env.setenv(key, value)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert f"error: {named}:" in capsys.readouterr().err


def test_the_worker_command_exits_2_on_a_bad_value():
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLASHMONO_")}
    env["PYTHONPATH"] = str(ROOT)
    result = subprocess.run([sys.executable, "-m", "worker.runtime.main", "--max-sessions", "0"], env=env,
                            capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 2 and "--max-sessions:" in result.stderr, result.stderr


@pytest.mark.parametrize(("env", "named"), [
    ({"FLASHMONO_MAX_QUEUE": "0"}, "FLASHMONO_MAX_QUEUE"),
    ({"FLASHMONO_REDIS_CONNECTIONS": "two"}, "FLASHMONO_REDIS_CONNECTIONS"),
    ({"FLASHMONO_API_KEYS": "k=write"}, "FLASHMONO_API_KEYS"),
    ({"FLASHMONO_REQUEST_TIMEOUT_S": "0"}, "FLASHMONO_REQUEST_TIMEOUT_S"),
])
def test_a_bad_gateway_value_names_its_variable(env, named):
    with pytest.raises(ValueError, match=f"^{named}: "):
        Settings.from_env(env)


def test_every_flashmono_variable_read_is_a_setting():
    pattern = re.compile(r"\bFLASHMONO_[A-Z0-9_]*[A-Z0-9]\b")
    found: dict[str, set[str]] = {}
    for folder in ("worker/runtime", "service"):
        for path in (ROOT / folder).rglob("*.py"):
            for name in pattern.findall(path.read_text()):
                found.setdefault(name, set()).add(str(path.relative_to(ROOT)))
    assert len(found) > 5  # the scan sees the sources (comments and docs name the variables too)
    settings = _env_names(WorkerSettings) | _env_names(Settings)
    unknown = {name: sorted(paths) for name, paths in found.items() if name not in settings | set(NOT_SETTINGS)}
    assert not unknown, f"FLASHMONO_* names that are no field of WorkerSettings or Settings: {unknown}"
    assert set(NOT_SETTINGS) <= set(found), sorted(set(NOT_SETTINGS) - set(found))  # no stale exceptions
    assert not set(NOT_SETTINGS) & settings


def test_the_readme_table_is_generated_from_the_models():
    readme = (ROOT / "README.md").read_text()
    assert readme_tables() in readme, "stale: run `python -m worker.runtime.settings --readme README.md`"
