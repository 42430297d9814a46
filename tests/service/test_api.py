"""REST API against a real gateway + Redis + worker: auth, session CRUD, fleet listing, health, metrics."""

from __future__ import annotations

from conftest import ADMIN_KEY, OTHER_STREAM_KEY, READ_KEY, STREAM_KEY, client_for
from service_helpers import ICL_INTRINSICS


def test_health_and_readiness(api):
    assert api.get("/healthz").json() == {"status": "ok"}
    ready = api.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["redis"] is True and ready.json()["workers"] >= 1


def test_missing_or_unknown_key_is_401_with_message(stack):
    with client_for(stack, None) as anonymous:
        r = anonymous.get("/v1/sessions")
        assert r.status_code == 401 and "missing API key" in r.json()["detail"]
    with client_for(stack, "not-a-key") as stranger:
        r = stranger.post("/v1/sessions", json={})
        assert r.status_code == 401 and r.json()["detail"] == "unknown API key"


def test_bearer_header_is_accepted(stack):
    with client_for(stack, None) as client:
        r = client.get("/v1/sessions", headers={"Authorization": f"Bearer {READ_KEY}"})
        assert r.status_code == 200


def test_scopes_and_ownership(api, stack):
    session = api.post("/v1/sessions", json={"name": "owned"}).json()
    sid = session["id"]
    with client_for(stack, READ_KEY) as reader, client_for(stack, OTHER_STREAM_KEY) as other, \
            client_for(stack, ADMIN_KEY) as admin:
        r = reader.post("/v1/sessions", json={})
        assert r.status_code == 403 and "stream" in r.json()["detail"]
        assert reader.get(f"/v1/sessions/{sid}").status_code == 200  # read scope reads any session
        assert reader.delete(f"/v1/sessions/{sid}").status_code == 403
        r = other.get(f"/v1/sessions/{sid}")
        assert r.status_code == 403 and "did not create" in r.json()["detail"]
        assert other.delete(f"/v1/sessions/{sid}").status_code == 403
        assert sid not in {s["id"] for s in other.get("/v1/sessions", params={"limit": 500}).json()["sessions"]}
        assert admin.get(f"/v1/sessions/{sid}").status_code == 200
        assert admin.delete(f"/v1/sessions/{sid}").status_code == 204
    r = api.get(f"/v1/sessions/{sid}")
    assert r.status_code == 404 and sid in r.json()["detail"]


def test_create_returns_the_full_session_record(api):
    body = {"intrinsics": ICL_INTRINSICS, "preset": "fast", "name": "kitchen", "device_id": "phone-7",
            "metadata": {"app": "1.2"}}
    r = api.post("/v1/sessions", json=body)
    assert r.status_code == 201
    s = r.json()
    assert s["status"] == "created" and s["name"] == "kitchen" and s["device_id"] == "phone-7"
    assert s["intrinsics"] == {**ICL_INTRINSICS} and s["metadata"] == {"app": "1.2"} and s["preset"] == "fast"
    assert s["frames_received"] == 0 and s["frames_processed"] == 0 and s["revision"] == 0
    assert api.get(f"/v1/sessions/{s['id']}").json()["created_at"] == s["created_at"]


def test_invalid_bodies_are_422_with_details(api):
    bad_principal_point = {**ICL_INTRINSICS, "cx": 500.0}
    r = api.post("/v1/sessions", json={"intrinsics": bad_principal_point})
    assert r.status_code == 422 and "principal point" in str(r.json()["detail"])
    r = api.post("/v1/sessions", json={"intrinsics": {**ICL_INTRINSICS, "fx": -1}})
    assert r.status_code == 422
    r = api.post("/v1/sessions", json={"colour": "blue"})
    assert r.status_code == 422 and "colour" in str(r.json()["detail"])
    r = api.post("/v1/sessions", json={"preset": "no such preset!"})
    assert r.status_code == 422


def test_listing_filters_and_cursor_pagination(stack):
    with client_for(stack, OTHER_STREAM_KEY) as owner:
        created = [owner.post("/v1/sessions", json={"device_id": "fleet-a" if i % 2 else "fleet-b",
                                                    "name": f"walk-{i}"}).json()["id"] for i in range(7)]
        a = owner.get("/v1/sessions", params={"device_id": "fleet-a"}).json()["sessions"]
        assert {s["id"] for s in a} == set(created[1::2])
        named = owner.get("/v1/sessions", params={"name": "walk-4"}).json()["sessions"]
        assert [s["id"] for s in named] == [created[4]]
        assert owner.get("/v1/sessions", params={"status": "finished", "device_id": "fleet-a"}).json()[
            "sessions"] == []
        seen, cursor, pages = [], None, 0
        while True:
            params = {"limit": 2, "device_id": "fleet-b"} | ({"cursor": cursor} if cursor else {})
            page = owner.get("/v1/sessions", params=params).json()
            seen += [s["id"] for s in page["sessions"]]
            pages += 1
            cursor = page["next_cursor"]
            if cursor is None:
                break
        assert seen == list(reversed(created[0::2]))  # newest first, each exactly once
        assert pages == 2
        assert owner.get("/v1/sessions", params={"limit": 0}).status_code == 422
        assert owner.get("/v1/sessions", params={"status": "bogus"}).status_code == 422


def test_unknown_session_is_404_everywhere(api):
    for path in ("", "/trajectory", "/map.ply", "/render?pose=" + ",".join(["0"] * 16)):
        r = api.get(f"/v1/sessions/nope{path}")
        assert r.status_code == 404, path
        assert "not found" in r.json()["detail"]
    assert api.delete("/v1/sessions/nope").status_code == 404


def test_metrics_expose_service_figures(admin, stack):
    text = admin.get("/metrics").text
    for name in ("flashmono_frames_ingested_total", "flashmono_ack_latency_seconds_bucket",
                 "flashmono_workers_alive", "flashmono_sessions{status=\"created\"}", "flashmono_queue_depth"):
        assert name in text, name
    with client_for(stack, STREAM_KEY) as streamer:
        assert streamer.get("/metrics").status_code == 403
