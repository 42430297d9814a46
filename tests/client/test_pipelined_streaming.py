"""Pipelined streaming at 30 FPS into a server that cannot keep up loses nothing and keeps the order.

A real stack (Redis, gateway under uvicorn, one worker) with a queue of 4 frames and a passthrough engine that takes
40 ms a frame (slower than 30 FPS), so backpressure is certain. Two senders stream 211 real ICL images (cycled)
without waiting for acks: the SDK, and an independent client written against the documented protocol only
(websockets + msgpack): on `backpressure` it rewinds to `resend_from`. Each frame's pose prior encodes its seq
(x translation), so the passthrough engine's reported pose proves which frame it processed."""

from __future__ import annotations

from pathlib import Path

import cv2
import httpx
import msgpack
import numpy as np
import pytest
from live_stack import LiveStack
from raw_stream_client import RawPipelinedClient

from client.sdk import FlashMonoClient
from client.streaming import WireOptions
from worker.data.frame import Frame

FRAMES = 211
FPS = 30.0
ICL_RGB = Path(__file__).resolve().parents[1] / "data" / "icl_mini" / "rgb"


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_MAX_QUEUE": "4", "FLASHMONO_PASSTHROUGH_DELAY_MS": "40"}
    with LiveStack(workers=1, engine="passthrough", extra_env=env) as live:
        yield live


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    paths = sorted(ICL_RGB.glob("*.jpg"))[:12]
    return [cv2.resize(cv2.imread(str(p))[..., ::-1], (160, 120), interpolation=cv2.INTER_AREA) for p in paths]


def _pose(seq: int) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = float(seq)
    return pose


def _check_session(stack: LiveStack, session_id: str, pose_seqs: list[int], pose_x: list[float]) -> None:
    assert pose_seqs == list(range(FRAMES)), "live poses are not every seq once, in order"
    assert pose_x == [float(s) for s in range(FRAMES)], "a pose belongs to another frame"
    with httpx.Client(base_url=stack.url, timeout=30) as api:
        session = api.get(f"/v1/sessions/{session_id}").json()
        assert session["status"] == "finished"
        assert session["frames_received"] == session["frames_processed"] == FRAMES
        poses = api.get(f"/v1/sessions/{session_id}/trajectory").json()["poses"]
    assert [p["seq"] for p in poses] == list(range(FRAMES))
    assert [p["pose"][3] for p in poses] == [float(s) for s in range(FRAMES)]
    assert [p["timestamp"] for p in poses] == pytest.approx([s / FPS for s in range(FRAMES)])


def test_sdk_streams_211_frames_at_30_fps_without_loss(stack, images) -> None:
    frames = [Frame(index=i, timestamp=i / FPS, image=images[i % len(images)], pose=_pose(i)) for i in range(FRAMES)]
    with FlashMonoClient(stack.url) as client:
        session = client.create_session(name="sdk-30fps", skip_frames=False)  # recorded: every frame counts
        summary = client.stream(session.id, frames, fps=FPS, window=8, max_pending=16,
                                wire=WireOptions(send_intrinsics=False, send_pose=True))
    assert summary.backpressure_retries > 0, "the server never refused a frame: the test proves nothing"
    assert summary.frames_dropped == 0 and summary.errors == []
    assert summary.frames_acked == FRAMES and summary.finished_frames == FRAMES
    _check_session(stack, session.id, [p.seq for p in summary.poses], [float(p.pose[0, 3]) for p in summary.poses])


def test_independent_client_streams_211_frames_at_30_fps_without_loss(stack, images) -> None:
    messages = []
    for seq in range(FRAMES):
        jpeg = cv2.imencode(".jpg", images[seq % len(images)][..., ::-1])[1].tobytes()
        messages.append(msgpack.packb({"type": "frame", "seq": seq, "timestamp": seq / FPS, "image": jpeg,
                                       "pose": _pose(seq).reshape(-1).tolist()}))
    with httpx.Client(base_url=stack.url, timeout=30) as api:
        session_id = api.post("/v1/sessions", json={"name": "raw-30fps", "skip_frames": False}).json()["id"]
    client = RawPipelinedClient(f"ws://127.0.0.1:{stack.port}/v1/sessions/{session_id}/stream", messages, FPS)
    client.run()
    assert client.rewinds > 0, "the server never refused a frame: the test proves nothing"
    assert client.acked == list(range(FRAMES)), "acks are not every seq once, in order"
    _check_session(stack, session_id, [p["seq"] for p in client.poses], [p["pose"][3] for p in client.poses])
