"""The contract and the server agree: schemathesis, driven by the committed openapi.yaml, against the served API (a
real stack: embedded Redis, the gateway under uvicorn with API keys on, one passthrough worker), in its coverage,
fuzzing and stateful phases, bounded, finds nothing.

Every default check runs (status codes, content types, response schemas and headers, server errors, positive and
negative data, the `Allow` header of 405s, auth that is not ignored, ...) plus one of ours (schemathesis_hooks.py).
Three rejections the schema cannot express are allowed for positive data (schemathesis.toml below): a session's
cross-field rules (422: the principal point inside the image, a rigid depth-to-colour extrinsic, a map that does not
exist), a render's pose that is well formed but not a camera pose, or a size over the pixel limit (400), and an
uploaded map whose bytes are no map package (400).

Bounds: FLASHMONO_SCHEMATHESIS_EXAMPLES cases per operation (default 60) and FLASHMONO_SCHEMATHESIS_SEED (default
a fixed one; `random` for a fresh one each run)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import yaml

pytest.importorskip("schemathesis")

from service.launcher import LocalStack  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
OPENAPI = REPO / "openapi.yaml"
HOOKS = Path(__file__).with_name("schemathesis_hooks.py")
ADMIN_KEY = "k-contract-admin"
API_KEYS = f"{ADMIN_KEY}=admin;k-contract-read=read"
WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LEASE_TTL_MS": "4000", "FLASHMONO_LOG_LEVEL": "WARNING"}
EXAMPLES = int(os.environ.get("FLASHMONO_SCHEMATHESIS_EXAMPLES", "60"))
SEED = os.environ.get("FLASHMONO_SCHEMATHESIS_SEED", "45")
ALWAYS_ACCEPTABLE = ["2xx", "3xx", "401", "403", "404", "409", "429", "5xx"]  # schemathesis' default list
CONFIG = f"""
[[operations]]
include-name = "POST /v1/sessions"
checks.positive_data_acceptance.expected-statuses = {json.dumps([*ALWAYS_ACCEPTABLE, "422"])}

[[operations]]
include-name = "GET /v1/sessions/{{session_id}}/render"
checks.positive_data_acceptance.expected-statuses = {json.dumps([*ALWAYS_ACCEPTABLE, "400"])}

[[operations]]
include-name = "POST /v1/maps"
checks.positive_data_acceptance.expected-statuses = {json.dumps([*ALWAYS_ACCEPTABLE, "400"])}
"""


def schemathesis_cli() -> str:
    found = Path(sys.executable).with_name("schemathesis")
    return str(found) if found.exists() else shutil.which("schemathesis") or "schemathesis"


@pytest.fixture(scope="module")
def stack():
    # the fuzzing creates many sessions with one key: no per-key limit, so that later tests can still create theirs
    gateway_env = {"FLASHMONO_API_KEYS": API_KEYS, "FLASHMONO_REQUEST_TIMEOUT_S": "10",
                   "FLASHMONO_MAX_LIVE_SESSIONS": "0"}
    with LocalStack(workers=1, gateway_env=gateway_env, worker_env=WORKER_ENV) as local:
        yield local


def test_the_committed_contract_is_the_served_one(stack):
    served = httpx.get(f"{stack.base_url}/openapi.json", timeout=10).json()
    committed = yaml.safe_load(OPENAPI.read_text())
    assert committed == served, "openapi.yaml is stale: run `python -m service.openapi_export`"


def test_schemathesis_finds_nothing(stack, tmp_path):
    (tmp_path / "schemathesis.toml").write_text(CONFIG)
    seed = [] if SEED == "random" else ["--seed", SEED]
    argv = [schemathesis_cli(), "--config-file", str(tmp_path / "schemathesis.toml"), "--no-color", "run",
            str(OPENAPI), "--url", stack.base_url, "-H", f"X-API-Key: {ADMIN_KEY}",
            "--phases", "coverage,fuzzing,stateful", "--max-examples", str(EXAMPLES), *seed, "--workers", "2",
            "--request-timeout", "30", "--generation-database", "none", "--suppress-health-check", "all",
            "--report", "ndjson", "--report-dir", str(tmp_path / "report")]
    env = {**os.environ, "SCHEMATHESIS_HOOKS": str(HOOKS), "PYTHONPATH": os.pathsep.join(
        p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)}
    run = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    output = run.stdout + run.stderr
    assert run.returncode == 0, output[-20000:]
    summary = output[output.find("SUMMARY"):]
    assert "Tested: 19" in summary and "Selected: 19/19" in summary, summary
    for phase in ("Coverage", "Fuzzing", "Stateful"):
        assert f"✅ {phase}" in summary, summary  # ran and passed (not skipped)
    cases = summary[summary.find("Test cases:"):].splitlines()[:2]
    print(" ".join(line.strip() for line in cases))


def test_what_the_run_found_once_stays_fixed(stack):
    """The findings of the first run, each asked directly: Allow of a 405, a session with no frame yet, a render pose
    the schema accepts, a body that is not UTF-8 (or not JSON), to either route that takes JSON."""
    with httpx.Client(base_url=stack.base_url, headers={"X-API-Key": ADMIN_KEY}, timeout=30) as api:
        assert api.request("OPTIONS", "/v1/sessions").headers["allow"] == "GET, POST"
        created = api.post("/v1/sessions", json={})
        assert created.status_code == 201, created.text
        sid = created.json()["id"]
        assert api.request("PATCH", f"/v1/sessions/{sid}").headers["allow"] == "DELETE, GET"
        for path in ("map", "map.ply"):
            answer = api.get(f"/v1/sessions/{sid}/{path}")
            assert answer.status_code == 409 and "no frame" in answer.json()["detail"], answer.text
        identity = "1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1"
        answer = api.get(f"/v1/sessions/{sid}/render", params={"pose": identity, "width": 8, "height": 8, "fx": 4,
                                                                 "fy": 4, "cx": 4, "cy": 4})
        assert answer.status_code == 409, answer.text
        for pose in ("", "1,0,0", "nan," * 15 + "nan"):
            answer = api.get(f"/v1/sessions/{sid}/render", params={"pose": pose})
            assert answer.status_code == 400 and "16 comma-separated" in answer.json()["detail"], answer.text
        answer = api.post("/v1/sessions", content=b'{"name": "\xff"}', headers={"content-type": "application/json"})
        assert answer.status_code == 400
        for path in ("/v1/sessions", "/v1/maps"):  # the maps route parses its JSON itself, the same way
            answer = api.post(path, content=b'R\xc6', headers={"content-type": "application/json"})
            assert answer.status_code == 400, (path, answer.text)
            answer = api.post(path, content=b'{"name": ', headers={"content-type": "application/json"})
            assert answer.status_code == 422 and answer.json()["detail"][0]["type"] == "json_invalid", answer.text
        assert api.post("/v1/sessions", json={"skip_frames": 0}).status_code == 422


def test_every_pose_the_schema_accepts_parses_into_16_numbers():
    hypothesis = pytest.importorskip("hypothesis")
    from hypothesis import strategies as st

    from service.routes_results import RENDER_POSE_PATTERN, render_params

    record = {"intrinsics": '{"fx": 50, "fy": 50, "cx": 16, "cy": 12, "width": 32, "height": 24}'}

    @hypothesis.settings(max_examples=300, deadline=None, database=None)
    @hypothesis.given(st.from_regex(RENDER_POSE_PATTERN))
    def parses(pose: str) -> None:
        try:
            params = render_params(record, pose, None, None, None, None, None, None, "color", 1 << 20)
        except Exception as err:  # refused for what it means (not rigid, not finite), never for its syntax
            assert "comma-separated" not in str(getattr(err, "detail", err)), pose
        else:
            assert len(params["pose"]) == 16

    parses()
