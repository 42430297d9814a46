"""Memory bounds: huge frames are decoded straight to the working resolution (a 8192x8192 first frame costs the
worker no per-pixel memory at full size), and a frame on which workers keep dying is quarantined instead of being
handed to worker after worker."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import httpx
import msgpack
import numpy as np
import pytest
import redis
from runtime_helpers import WORKER_ENV, receive_until, synthetic_frame, wait_for
from websockets.sync.client import connect

from protocol import keys
from service.launcher import LocalStack
from worker.runtime.frames import decode_frame, working_size
from worker.runtime.memory import over_budget, resident_mb

REPO_ROOT = Path(__file__).resolve().parents[2]


def smooth_jpeg(width: int, height: int) -> bytes:
    """A legal, highly compressible JPEG (a gradient): tens of kB on the wire for tens of megapixels."""
    x = np.linspace(0, 255, width, dtype=np.float32)[None, :]
    y = np.linspace(0, 255, height, dtype=np.float32)[:, None]
    image = np.empty((height, width, 3), np.uint8)
    image[..., 0] = x
    image[..., 1] = y
    image[..., 2] = 128
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 50])[1].tobytes()


@pytest.fixture(scope="module")
def huge_jpegs(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("huge")
    paths = {}
    for name, (w, h) in {"4096x3072": (4096, 3072), "8192x8192": (8192, 8192)}.items():
        paths[name] = out / f"{name}.jpg"
        paths[name].write_bytes(smooth_jpeg(w, h))
    return paths


def test_working_size():
    assert working_size(320, 240, None) == (320, 240)
    assert working_size(4096, 3072, None) == (640, 480)
    assert working_size(8192, 8192, None, max_side=512) == (512, 512)
    assert working_size(4096, 3072, {"width": 320, "height": 240}) == (320, 240)
    assert working_size(160, 120, {"width": 320, "height": 240}) == (160, 120)  # never up


def test_decode_brings_frames_to_the_working_resolution(huge_jpegs):
    message = {"seq": 0, "timestamp": 0.0, "image": huge_jpegs["4096x3072"].read_bytes(),
               "intrinsics": [3000.0, 3000.0, 2048.0, 1536.0]}
    frame = decode_frame(message, None)
    assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
    k = frame.intrinsics
    assert (k.width, k.height) == (640, 480)
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx((3000 * 640 / 4096, 3000 * 480 / 3072, 320.0, 240.0))
    assert frame.image[:, 0, 2].mean() < 5 and frame.image[:, -1, 2].mean() > 250  # the gradient (blue), not garbage
    # depth comes down with nearest neighbours: no invented values between a surface and a hole
    depth = np.zeros((3072, 4096), np.uint16)
    depth[:, 2048:] = 1500
    message["depth"] = cv2.imencode(".png", depth)[1].tobytes()
    frame = decode_frame(message, {"width": 320, "height": 240, "fx": 1, "fy": 1, "cx": 1, "cy": 1})
    assert frame.depth.shape == (240, 320) and set(np.unique(frame.depth).tolist()) == {0.0, 1.5}


@pytest.mark.parametrize("name", ["4096x3072", "8192x8192"])
def test_decoding_a_huge_frame_stays_small_in_memory(huge_jpegs, name):
    """Peak resident memory of a fresh process decoding the frame: a full-size decode alone would add
    width*height*3 bytes (36-192 MiB here), twice with the colour conversion."""
    code = f"""
import resource, sys
from pathlib import Path
from worker.runtime.frames import decode_frame
data = Path({str(huge_jpegs[name])!r}).read_bytes()
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
frame = decode_frame({{"seq": 0, "timestamp": 0.0, "image": data}}, None)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(frame.image.shape[1], frame.image.shape[0], (after - before) / 1024)
"""
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    width, height, grown_mb = out.stdout.split()
    assert max(int(width), int(height)) == 640
    assert float(grown_mb) < 24, f"decoding grew the peak by {grown_mb} MiB"


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def test_huge_first_frames_through_the_service(huge_jpegs):
    with LocalStack(workers=1, worker_env=WORKER_ENV) as stack, httpx.Client(base_url=stack.base_url) as api:
        for name in ("4096x3072", "8192x8192"):
            sid = api.post("/v1/sessions", json={"name": name}).json()["id"]
            peak_before = _peak_rss_mb(stack.workers[0].pid)
            with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
                image = huge_jpegs[name].read_bytes()
                for seq in range(4):
                    ws.send(msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / 30, "image": image}))
                ws.send(json.dumps({"type": "finish"}))
                messages = receive_until(ws, lambda m: m["type"] == "finished", timeout_s=60)
            assert sorted(m["seq"] for m in messages if m["type"] == "pose") == [0, 1, 2, 3]
            assert api.get(f"/v1/sessions/{sid}").json()["status"] == "finished"
            assert _peak_rss_mb(stack.workers[0].pid) - peak_before < 40


def test_a_frame_that_kills_its_workers_is_quarantined():
    env = {**WORKER_ENV, "FLASHMONO_PASSTHROUGH_DELAY_MS": "8000", "FLASHMONO_LEASE_TTL_MS": "2500"}
    with LocalStack(workers=0, worker_env=env) as stack, httpx.Client(base_url=stack.base_url) as api:
        r = redis.Redis.from_url(stack.redis_url)
        sid = api.post("/v1/sessions", json={"name": "poison"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=20) as ws:
            ws.send(synthetic_frame(0))
            assert receive_until(ws, lambda m: m["type"] in ("ack", "error"))[-1]["type"] == "ack"
            workers = {f"w{i}": stack.add_worker(worker_id=f"w{i}") for i in range(3)}
            for attempt in (1, 2):
                # the frame is in the engine (8 s of simulated compute) when its worker dies
                wait_for(lambda a=attempt: r.get(keys.inflight(sid)) == f"0:{a}".encode(), timeout_s=60)
                victim = workers.pop(r.get(keys.lease(sid)).decode())
                victim.send_signal(signal.SIGKILL)
                victim.wait()
            messages = receive_until(ws, lambda m: m["type"] == "error" and m.get("code") == "engine_failed",
                                     timeout_s=60)
        assert "quarantined" in messages[-1]["message"] and "died 2 times" in messages[-1]["message"]
        session = api.get(f"/v1/sessions/{sid}").json()
        assert session["status"] == "failed" and "frame 0 was quarantined" in session["error"]
        assert session["frames_processed"] == 0
        assert r.get(keys.inflight(sid)) == b"0:3"  # the third worker refused it without processing it
        assert [w.poll() for w in workers.values()] == [None]  # and lives on


def test_memory_budget():
    assert 10 < resident_mb() < 100_000
    assert over_budget(1) and not over_budget(0) and not over_budget(10**7)
