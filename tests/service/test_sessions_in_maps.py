"""Sessions in a saved map over the real stack (embedded Redis, the gateway under uvicorn, one worker with the real
SLAM engine): a `localize` session relocalizes in the map and publishes its poses in the map's world, an `extend`
session makes a new version of the map, another scene stays "not relocalized", a map deleted before a session's
first frame fails that session with a message, and every other session goes on; a worker killed under a session in a
map hands it to another, which goes on in the map's world."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
import redis
from service_helpers import ICL_INTRINSICS, frame_message, icl_frames, of_type, receive_until
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack

FRAMES = 16
TUM_DIR = Path(__file__).resolve().parent.parent / "data" / "tum_fr1_rpy_mini"


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_LEASE_TTL_MS": "10000", "FLASHMONO_TORCH_THREADS": "2",
           "FLASHMONO_LOG_LEVEL": "WARNING", "FLASHMONO_SNAPSHOT_EVERY": "1"}
    with LocalStack(workers=1, worker_env=env, gateway_env={"FLASHMONO_REQUEST_TIMEOUT_S": "120"}) as local:
        yield local


def wait_for(condition, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.1)


def api(stack: LocalStack) -> httpx.Client:
    return httpx.Client(base_url=stack.base_url, timeout=180)


def stream(stack: LocalStack, body: dict, frames: list[dict]) -> tuple[str, list[dict]]:
    """A session created with `body`, the RGB-D `frames` streamed and finished; (its id, every message)."""
    with api(stack) as http:
        created = http.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS, "preset": "rgbd", **body})
        assert created.status_code == 201, created.text
        sid = created.json()["id"]
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
        for seq, frame in enumerate(frames):
            ws.send(frame_message(seq, frame, with_depth=True))
        ws.send(json.dumps({"type": "finish"}))
        messages = receive_until(ws, lambda m: m["type"] in ("finished", "error") and "seq" not in m,
                                 timeout_s=300)
    return sid, messages


def trajectory(stack: LocalStack, sid: str) -> dict[int, np.ndarray]:
    with api(stack) as http:
        poses = http.get(f"/v1/sessions/{sid}/trajectory").json()["poses"]
    return {p["seq"]: np.asarray(p["pose"], np.float64).reshape(4, 4) for p in poses}


def other_scene_frames() -> list[dict]:
    """Ten TUM fr1/rpy frames (another room) in the wire's units (depth PNG in millimetres)."""
    rows = [line.split() for line in (TUM_DIR / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    depth_rows = [line.split() for line in (TUM_DIR / "depth.txt").read_text().splitlines()
                  if not line.startswith("#")]
    frames = []
    for (stamp, rgb), (_, depth) in zip(rows, depth_rows):
        raw = cv2.imread(str(TUM_DIR / depth), cv2.IMREAD_UNCHANGED).astype(np.float64)
        millimetres = np.round(raw / 5.0).astype(np.uint16)  # 5000 units a metre -> 1000
        frames.append({"jpeg": (TUM_DIR / rgb).read_bytes(), "depth": cv2.imencode(".png", millimetres)[1].tobytes(),
                       "timestamp": float(stamp)})
    return frames


@pytest.fixture(scope="module")
def saved_map(stack) -> tuple[str, str]:
    """(map id, the id of the session that built it): 16 ICL frames, RGB-D."""
    sid, messages = stream(stack, {"name": "builder"}, icl_frames(FRAMES))
    assert of_type(messages, "finished") and not of_type(messages, "error")
    with api(stack) as http:
        created = http.post("/v1/maps", json={"session_id": sid, "name": "living room"})
    assert created.status_code == 201, created.text
    return created.json()["id"], sid


def test_a_localize_session_publishes_its_poses_in_the_maps_world(stack, saved_map) -> None:
    map_id, builder = saved_map
    sid, messages = stream(stack, {"map_id": map_id}, icl_frames(FRAMES)[::-1])  # the room, walked backwards
    relocalized = [m for m in of_type(messages, "relocalized") if m.get("map_id") == map_id]
    assert len(relocalized) == 1 and relocalized[0]["inliers"] >= 40
    built, here = trajectory(stack, builder), trajectory(stack, sid)
    # frame seq here is frame FRAMES-1-seq there: the same camera, now in the builder's world
    gaps = [np.linalg.norm(here[s][:3, 3] - built[FRAMES - 1 - s][:3, 3]) for s in here]
    assert max(gaps) < 0.05, gaps
    with api(stack) as http:
        session = http.get(f"/v1/sessions/{sid}").json()
        assert session["map_id"] == map_id and session["map_mode"] == "localize"
        assert session["tracking_state"] == "tracking"
        used = http.get(f"/v1/maps/{map_id}/sessions").json()["sessions"]
        assert {"id": sid, "role": "used"}.items() <= next(s for s in used if s["id"] == sid).items()
        assert http.get(f"/v1/maps/{map_id}").json()["latest_version"] == 1  # localize adds nothing
        render = http.get(f"/v1/sessions/{sid}/render", params={"pose": ",".join(map(str, built[0].reshape(-1)))})
        assert render.status_code == 200 and render.headers["content-type"] == "image/png"


def test_an_extend_session_makes_a_new_version(stack, saved_map) -> None:
    map_id, _ = saved_map
    with api(stack) as http:
        before = http.get(f"/v1/maps/{map_id}").json()
    frames = icl_frames(FRAMES + 12)[8:]  # half the room again, then further on
    _, messages = stream(stack, {"map_id": map_id, "map_mode": "extend"}, frames)
    extended = of_type(messages, "map_extended")
    assert len(extended) == 1 and extended[0]["version"] == before["latest_version"] + 1, messages[-5:]
    with api(stack) as http:
        after = http.get(f"/v1/maps/{map_id}").json()
    assert after["latest_version"] == before["latest_version"] + 1 and len(after["versions"]) == 2
    assert after["meta"]["keyframes"] > before["meta"]["keyframes"]
    assert after["meta"]["surfels"] > before["meta"]["surfels"]


def test_another_scene_is_never_relocalized_and_extends_nothing(stack, saved_map) -> None:
    map_id, _ = saved_map
    with api(stack) as http:
        before = http.get(f"/v1/maps/{map_id}").json()["latest_version"]
    sid, messages = stream(stack, {"map_id": map_id, "map_mode": "extend"}, other_scene_frames())
    assert not [m for m in of_type(messages, "relocalized") if m.get("map_id")]
    assert of_type(messages, "map_not_extended") and of_type(messages, "finished")
    with api(stack) as http:
        assert http.get(f"/v1/maps/{map_id}").json()["latest_version"] == before
        assert http.get(f"/v1/sessions/{sid}").json()["tracking_state"] == "not_relocalized"


def test_a_session_whose_map_was_deleted_fails_and_says_why(stack, saved_map) -> None:
    _, builder = saved_map
    with api(stack) as http:
        doomed = http.post("/v1/maps", json={"session_id": builder, "name": "doomed"}).json()["id"]
        sid = http.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS, "preset": "rgbd",
                                              "map_id": doomed}).json()["id"]
        assert http.delete(f"/v1/maps/{doomed}").status_code == 204
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
        ws.send(frame_message(0, icl_frames(1)[0], with_depth=True))
        messages = receive_until(ws, lambda m: m["type"] == "error" and "seq" not in m, timeout_s=120)
    assert doomed in of_type(messages, "error")[-1]["message"]
    with api(stack) as http:
        assert http.get(f"/v1/sessions/{sid}").json()["status"] == "failed"
        assert http.get(f"/v1/sessions/{builder}").json()["status"] == "finished"


def test_a_session_in_a_map_survives_its_worker_killed(stack, saved_map) -> None:
    """Last in this module: it kills the module's first worker (a second one takes the session over)."""
    map_id, builder = saved_map
    r = redis.Redis.from_url(stack.redis_url)
    frames = icl_frames(3 * FRAMES)  # the map's frames first, then further on
    with api(stack) as http:
        sid = http.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS, "preset": "rgbd",
                                              "map_id": map_id}).json()["id"]
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
        messages: list[dict] = []
        seq = 0

        def anchored_in_a_snapshot() -> bool:
            found = [m for m in of_type(messages, "relocalized") if m.get("map_id") == map_id]
            return bool(found) and int(r.hget(keys.snapshot(sid), "seq") or -1) >= found[0]["seq"]

        while not anchored_in_a_snapshot():  # frame by frame until a snapshot holds the anchoring
            assert seq < len(frames) - 3, "no snapshot of the session anchored in the map"
            ws.send(frame_message(seq, frames[seq], with_depth=True))
            messages += receive_until(ws, lambda m, s=seq: m["type"] == "pose" and m["seq"] == s, timeout_s=60)
            time.sleep(0.1)  # a phone's pace: the snapshot in flight gets its turn
            seq += 1
        first = stack.workers[0]
        stack.add_worker(worker_id="maps-b")
        first.send_signal(signal.SIGKILL)
        first.wait()
        for rest, frame in enumerate(frames[seq:], start=seq):
            ws.send(frame_message(rest, frame, with_depth=True))
        ws.send(json.dumps({"type": "finish"}))
        messages += receive_until(ws, lambda m: m["type"] == "finished", timeout_s=300)
    assert len([m for m in of_type(messages, "relocalized") if m.get("map_id") == map_id]) == 1
    with api(stack) as http:
        assert http.get(f"/v1/sessions/{sid}").json()["worker"] == "maps-b"
    built, here = trajectory(stack, builder), trajectory(stack, sid)
    assert sorted(here) == list(range(len(frames)))
    assert max(np.linalg.norm(here[s][:3, 3] - built[s][:3, 3]) for s in built) < 0.05  # still the map's world
