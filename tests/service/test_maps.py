"""Maps as a resource over the real stack (embedded Redis, the gateway under uvicorn, one worker with the real SLAM
engine): a finished RGB-D session's map saved, listed, read, exported, uploaded again, served as splats and deleted;
scopes; corrupt uploads; sessions created in a map; a worker adding a version."""

from __future__ import annotations

import gzip
import json

import httpx
import pytest
import redis
from map_samples import synthetic_package_bytes
from service_helpers import ICL_INTRINSICS, frame_message, icl_frames, of_type, receive_until
from websockets.sync.client import connect

from protocol import keys
from protocol.map_package import CONTENT_TYPE, decode_package
from protocol.splats.ply_records import read_vertex_records
from service.launcher import LocalStack
from worker.maps import add_version, read_package
from worker.tracking.vo_config import VisualOdometryConfig

STREAM, OTHER, READ, ADMIN = "m-stream", "m-stream-2", "m-read", "m-admin"
API_KEYS = f"{STREAM}=stream;{OTHER}=stream;{READ}=read;{ADMIN}=admin"
FRAMES = 10
SCALE = 0.5  # 160x120
INTRINSICS = {k: (v * SCALE if k in ("fx", "fy", "cx", "cy") else int(v * SCALE)) for k, v in ICL_INTRINSICS.items()}
MAX_MAP_BYTES = 4 * 1024 * 1024


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_LEASE_TTL_MS": "10000", "FLASHMONO_TORCH_THREADS": "2",
           "FLASHMONO_LOG_LEVEL": "WARNING"}
    gateway = {"FLASHMONO_API_KEYS": API_KEYS, "FLASHMONO_REQUEST_TIMEOUT_S": "120",
               "FLASHMONO_MAX_MAP_BYTES": str(MAX_MAP_BYTES)}
    with LocalStack(workers=1, worker_env=env, gateway_env=gateway) as local:
        yield local


def client(stack: LocalStack, key: str | None = STREAM) -> httpx.Client:
    return httpx.Client(base_url=stack.base_url, headers={"X-API-Key": key} if key else {}, timeout=180)


@pytest.fixture(scope="module")
def session_id(stack) -> str:
    """A finished real RGB-D session (10 ICL frames at 160x120, preset rgbd) of the STREAM key."""
    with client(stack) as api:
        sid = api.post("/v1/sessions", json={"intrinsics": INTRINSICS, "preset": "rgbd", "name": "icl"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30,
                     additional_headers={"X-API-Key": STREAM}) as ws:
            for seq, frame in enumerate(icl_frames(FRAMES, scale=SCALE)):
                ws.send(frame_message(seq, frame, with_depth=True))
            ws.send(json.dumps({"type": "finish"}))
            messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=240)
        assert not of_type(messages, "error"), of_type(messages, "error")
        assert api.get(f"/v1/sessions/{sid}").json()["status"] == "finished"
    return sid


@pytest.fixture(scope="module")
def saved(stack, session_id) -> dict:
    """The session's map, saved by its key."""
    with client(stack) as api:
        created = api.post("/v1/maps", json={"session_id": session_id, "name": "living room"})
    assert created.status_code == 201, created.text
    return created.json()


def map_keys(stack: LocalStack, map_id: str) -> list[bytes]:
    return list(redis.Redis.from_url(stack.redis_url).scan_iter(match=f"fm:{{map.{map_id}}}:*"))


def test_a_finished_sessions_map_is_saved_read_exported_and_deleted(stack, session_id, saved):
    meta = saved["meta"]
    assert saved["name"] == meta["name"] == "living room" and saved["status"] == "ready"
    assert saved["latest_version"] == 1 and meta["scale"] == "metric" and meta["mode"] == "rgbd"
    assert meta["sessions"] == [session_id] and meta["keyframes"] >= 2 and meta["surfels"] > 1000
    assert meta["camera"]["width"] == 160 and meta["camera"]["fx"] == pytest.approx(INTRINSICS["fx"])
    assert all(lo < hi for lo, hi in zip(meta["bounds"]["min"], meta["bounds"]["max"]))
    assert saved["versions"] == [{"version": 1, "created_at": saved["created_at"], "size_bytes": saved["size_bytes"],
                                  "session_id": session_id, "meta": meta}]
    assert saved["sessions"] == [{"id": session_id, "role": "built", "map_mode": None, "status": "finished"}]
    with client(stack) as api:
        map_id = saved["id"]
        assert api.get(f"/v1/maps/{map_id}").json() == saved
        assert map_id in [m["id"] for m in api.get("/v1/maps").json()["maps"]]
        exported = api.get(f"/v1/maps/{map_id}/export")
        assert exported.status_code == 200 and exported.headers["content-type"] == CONTENT_TYPE
        assert len(exported.content) == saved["size_bytes"] and decode_package(exported.content).meta() == meta
        assert api.get(f"/v1/maps/{map_id}/sessions").json() == {"map_id": map_id, "sessions": saved["sessions"]}

        copy = api.post("/v1/maps", json={"session_id": session_id, "name": "to delete"}).json()
        assert map_keys(stack, copy["id"])
        assert api.delete(f"/v1/maps/{copy['id']}").status_code == 204
        assert api.get(f"/v1/maps/{copy['id']}").status_code == 404
        assert api.get(f"/v1/maps/{copy['id']}/export").status_code == 404
        assert api.delete(f"/v1/maps/{copy['id']}").status_code == 404
        assert copy["id"] not in [m["id"] for m in api.get("/v1/maps").json()["maps"]]
        assert map_keys(stack, copy["id"]) == []  # every version and key gone


def test_an_exported_map_uploaded_again_has_the_same_metadata(stack, saved):
    with client(stack) as api:
        data = api.get(f"/v1/maps/{saved['id']}/export").content
        uploaded = api.post("/v1/maps", content=data, headers={"content-type": CONTENT_TYPE})
        assert uploaded.status_code == 201, uploaded.text
        again = uploaded.json()
        assert again["id"] != saved["id"] and again["name"] == "living room" and again["meta"] == saved["meta"]
        assert again["versions"][0]["session_id"] is None and again["sessions"] == []  # built elsewhere
        assert api.get(f"/v1/maps/{again['id']}/export").content == data
        renamed = api.post("/v1/maps", params={"name": "copy"}, content=data,
                           headers={"content-type": "application/octet-stream"}).json()
        assert renamed["name"] == "copy" and renamed["meta"] == saved["meta"]
        for map_id in (again["id"], renamed["id"]):
            assert api.delete(f"/v1/maps/{map_id}").status_code == 204


def test_the_map_is_served_in_the_formats_sessions_serve(stack, saved):
    surfels = saved["meta"]["surfels"]
    with client(stack, READ) as api:  # a read key reads every map
        ply = api.get(f"/v1/maps/{saved['id']}/map")
        assert ply.status_code == 200 and ply.headers["x-map-format"] == "ply"
        records = read_vertex_records(ply.content)
        assert len(records) == surfels and "keyframe_id" not in records.dtype.names  # as sessions serve it
        assert "f_rest_0" not in records.dtype.names
        assert len(read_vertex_records(api.get(f"/v1/maps/{saved['id']}/map", params={"sh_degree": 3}).content
                                       ).dtype.names) == len(records.dtype.names) + 45
        splat = api.get(f"/v1/maps/{saved['id']}/map", params={"format": "splat"}).content
        assert len(splat) == 32 * surfels
        spz = gzip.decompress(api.get(f"/v1/maps/{saved['id']}/map", params={"format": "spz"}).content)
        assert int.from_bytes(spz[8:12], "little") == surfels
        assert api.get(f"/v1/maps/{saved['id']}/map", params={"version": 9}).status_code == 404
        assert api.get(f"/v1/maps/{saved['id']}/map", params={"format": "obj"}).status_code == 422


def test_other_keys_get_403_and_do_not_see_the_map(stack, saved, session_id):
    map_id = saved["id"]
    with client(stack, OTHER) as other, client(stack, READ) as reader, client(stack, None) as anonymous:
        for path in (f"/v1/maps/{map_id}", f"/v1/maps/{map_id}/export", f"/v1/maps/{map_id}/map",
                     f"/v1/maps/{map_id}/sessions"):
            assert other.get(path).status_code == 403, path
            assert reader.get(path).status_code == 200, path
            assert anonymous.get(path).status_code == 401, path
        assert other.delete(f"/v1/maps/{map_id}").status_code == 403
        assert reader.delete(f"/v1/maps/{map_id}").status_code == 403  # lacks the stream scope
        assert map_id not in [m["id"] for m in other.get("/v1/maps").json()["maps"]]
        assert map_id in [m["id"] for m in reader.get("/v1/maps").json()["maps"]]
        refused = other.post("/v1/maps", json={"session_id": session_id, "name": "mine now"})
        assert refused.status_code == 403 and "did not create this session" in refused.json()["detail"]
        assert reader.post("/v1/maps", json={"session_id": session_id, "name": "x"}).status_code == 403
        assert other.get("/v1/maps/0123456789abcdef0123456789abcdef").status_code == 404


def test_a_map_is_saved_only_from_a_finished_session(stack):
    with client(stack) as api:
        created = api.post("/v1/sessions", json={"name": "not yet"}).json()["id"]
        refused = api.post("/v1/maps", json={"session_id": created, "name": "x"})
        assert refused.status_code == 409 and "is created" in refused.json()["detail"]
        assert "finish it first" in refused.json()["detail"]
        assert api.post("/v1/maps", json={"session_id": "f" * 32, "name": "x"}).status_code == 404
        assert api.post("/v1/maps", json={"session_id": created}).status_code == 422  # no name
        assert api.post("/v1/maps", content=b"name=x", headers={"content-type": "text/plain"}).status_code == 415


def test_a_corrupt_upload_is_refused_with_why_and_nothing_is_stored(stack, saved):
    index = redis.Redis.from_url(stack.redis_url)
    before = (index.zcard(keys.MAPS_INDEX), index.dbsize())
    data = synthetic_package_bytes()
    with client(stack) as api:
        for corrupt, why in ((data[:-7], "corrupt map package"), (b"\x00" * 64, "msgpack"),
                             (data.replace(b"flashmono.map/1", b"flashmono.map/9"), "format")):
            refused = api.post("/v1/maps", content=corrupt, headers={"content-type": CONTENT_TYPE})
            assert refused.status_code == 400 and why in refused.json()["detail"], refused.text
        too_big = api.post("/v1/maps", content=b"\x00" * (MAX_MAP_BYTES + 1), headers={"content-type": CONTENT_TYPE})
        assert too_big.status_code == 413
    assert (index.zcard(keys.MAPS_INDEX), index.dbsize()) == before


def test_sessions_start_in_a_map_with_its_latest_version(stack, saved):
    map_id = saved["id"]
    with client(stack) as api, client(stack, OTHER) as other:
        session = api.post("/v1/sessions", json={"map_id": map_id, "name": "relocalize"})
        assert session.status_code == 201, session.text
        body = session.json()
        assert (body["map_id"], body["map_version"], body["map_mode"]) == (map_id, 1, "localize")
        record = redis.Redis.from_url(stack.redis_url).hgetall(keys.session(body["id"]))
        assert (record[b"map_id"], record[b"map_version"], record[b"map_mode"]) == (map_id.encode(), b"1",
                                                                                     b"localize")
        extend = api.post("/v1/sessions", json={"map_id": map_id, "map_mode": "extend"}).json()
        assert extend["map_mode"] == "extend" and api.get(f"/v1/sessions/{extend['id']}").json()["map_version"] == 1
        used = {s["id"]: s for s in api.get(f"/v1/maps/{map_id}/sessions").json()["sessions"] if s["role"] == "used"}
        assert used[body["id"]]["map_mode"] == "localize" and used[extend["id"]]["status"] == "created"
        plain = api.post("/v1/sessions", json={}).json()
        assert (plain["map_id"], plain["map_version"], plain["map_mode"]) == (None, None, None)

        no_map = api.post("/v1/sessions", json={"map_mode": "extend"})
        assert no_map.status_code == 422 and "map_mode needs map_id" in json.dumps(no_map.json())
        unknown = api.post("/v1/sessions", json={"map_id": "0" * 32})
        assert unknown.status_code == 422 and "unknown map" in json.dumps(unknown.json())
        assert api.post("/v1/sessions", json={"map_id": map_id, "map_mode": "merge"}).status_code == 422
        assert other.post("/v1/sessions", json={"map_id": map_id}).status_code == 403
        assert other.post("/v1/sessions", json={"map_id": map_id, "map_mode": "extend"}).status_code == 403
        for sid in (body["id"], extend["id"], plain["id"]):
            api.delete(f"/v1/sessions/{sid}")
    with client(stack, ADMIN) as admin:  # admin may read (and extend) every map
        assert admin.post("/v1/sessions", json={"map_id": map_id, "map_mode": "extend"}).status_code == 201


def test_a_worker_adds_a_version_and_the_old_one_is_kept(stack, saved, session_id):
    with client(stack) as api:
        copy = api.post("/v1/maps", json={"session_id": session_id, "name": "extended"}).json()
        worker_redis = redis.Redis.from_url(stack.redis_url)
        first = read_package(worker_redis, copy["id"])
        second = synthetic_package_bytes(name="extended")
        assert add_version(worker_redis, copy["id"], second, "e" * 32) == 2
        assert read_package(worker_redis, copy["id"]) == second and read_package(worker_redis, copy["id"], 1) == first
        got = api.get(f"/v1/maps/{copy['id']}").json()
        assert got["latest_version"] == 2 and [v["version"] for v in got["versions"]] == [1, 2]
        assert got["versions"][1]["session_id"] == "e" * 32 and got["meta"]["surfels"] == 200
        assert got["size_bytes"] == len(second) and got["versions"][0]["meta"]["surfels"] == saved["meta"]["surfels"]
        assert api.get(f"/v1/maps/{copy['id']}/export", params={"version": 1}).content == first
        assert api.get(f"/v1/maps/{copy['id']}/export").content == second
        assert api.get(f"/v1/maps/{copy['id']}/export", params={"version": 3}).status_code == 404
        assert api.delete(f"/v1/maps/{copy['id']}").status_code == 204
        assert map_keys(stack, copy["id"]) == []


def test_the_listing_pages_and_skips_a_map_deleted_while_listed(stack, saved):
    with client(stack, OTHER) as api:  # its own maps only
        ids = [api.post("/v1/maps", params={"name": f"m{i}"}, content=synthetic_package_bytes(seed=i),
                        headers={"content-type": CONTENT_TYPE}).json()["id"] for i in range(3)]
        first = api.get("/v1/maps", params={"limit": 2}).json()
        assert [m["id"] for m in first["maps"]] == ids[::-1][:2] and first["next_cursor"]
        assert api.delete(f"/v1/maps/{ids[0]}").status_code == 204
        second = api.get("/v1/maps", params={"limit": 2, "cursor": first["next_cursor"]}).json()
        assert second == {"maps": [], "next_cursor": None}
        listed = api.get("/v1/maps").json()["maps"]
        assert [m["name"] for m in listed] == ["m2", "m1"] and all(m["meta"]["keyframes"] == 3 for m in listed)
        for map_id in ids[1:]:
            api.delete(f"/v1/maps/{map_id}")


def test_the_package_size_of_the_test_session(saved):
    """What a map of 10 RGB-D frames at 160x120 weighs: its surfels (72 bytes each: 17 floats and the keyframe id)
    and, per keyframe, a JPEG, the float16 depth at half resolution (80 x 60 x 2 bytes) and its places (each ORB
    corner with a depth: 64 bytes of keypoint, descriptor and world point; a bag of 1,000 float32 words)."""
    meta = saved["meta"]
    surfels = meta["surfels"] * 72
    places = VisualOdometryConfig().n_features * 64 + 4_000
    assert surfels < saved["size_bytes"] < surfels + meta["keyframes"] * (80 * 60 * 2 + 30_000 + places)
    print(f"package {saved['size_bytes']} bytes: {meta['surfels']} surfels, {meta['keyframes']} keyframes")
