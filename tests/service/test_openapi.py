"""openapi.yaml is the schema the gateway serves, WebSocket protocol included."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from service.openapi_export import current_schema

OPENAPI = Path(__file__).resolve().parents[2] / "openapi.yaml"


def test_openapi_yaml_equals_the_served_schema():
    on_disk = yaml.safe_load(OPENAPI.read_text())
    served = json.loads(json.dumps(current_schema()))
    assert on_disk == served, "openapi.yaml is stale: run `python -m service.openapi_export`"


def test_schema_documents_every_route_and_the_websocket_protocol():
    schema = current_schema()
    paths = schema["paths"]
    assert set(paths["/v1/sessions"]) == {"get", "post"}
    assert set(paths["/v1/sessions/{session_id}"]) == {"get", "delete"}
    for path in ("trajectory", "render", "map.ply"):
        assert "get" in paths[f"/v1/sessions/{{session_id}}/{path}"]
    for path in ("/healthz", "/readyz", "/metrics"):
        assert path in paths
    listing = {p["name"] for p in paths["/v1/sessions"]["get"]["parameters"]}
    assert listing >= {"status", "device_id", "name", "limit", "cursor"}
    assert {"APIKeyHeader", "HTTPBearer"} <= set(schema["components"]["securitySchemes"])
    ws = schema["x-websocket"]["/v1/sessions/{session_id}/stream"]
    assert set(ws["client_messages"]) == {"frame", "finish", "ping"}
    assert {"ack", "pose", "loop_closed", "error", "finished"} <= set(ws["server_messages"])
    assert "backpressure" in ws["server_messages"]["error"]["properties"]["code"]["enum"]
