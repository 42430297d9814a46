"""Tracking events reach the client: RGB-D frames without poses streamed to a real stack (gateway, worker with the
real engine, Redis); a black frame with no depth gives a `tracking_lost` message at its seq and the pose of the
frame before it, the next real frame a `relocalized` message, and every pose stays finite; the SDK hands them to
`on_event` and the stream summary as TrackingEvents."""

from __future__ import annotations

import cv2
import httpx
import numpy as np
import pytest
from service_helpers import ICL_DIR, ICL_INTRINSICS, frame_message, icl_frames, of_type, receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

FRAMES = 8
BLACK = 4
SCALE = 0.5
INTRINSICS = {k: (v * SCALE if k in ("fx", "fy", "cx", "cy") else int(v * SCALE)) for k, v in ICL_INTRINSICS.items()}


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_TORCH_THREADS": "1", "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=env) as running:
        yield running


def test_lost_and_relocalized_messages_over_the_websocket(stack) -> None:
    frames = icl_frames(FRAMES, scale=SCALE)
    black = dict(frames[BLACK])
    black["jpeg"] = cv2.imencode(".jpg", np.zeros((120, 160, 3), np.uint8))[1].tobytes()
    black["depth"] = cv2.imencode(".png", np.zeros((120, 160), np.uint16))[1].tobytes()
    frames[BLACK] = black
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"intrinsics": INTRINSICS, "preset": "fast"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            for seq, frame in enumerate(frames):
                ws.send(frame_message(seq, frame, with_depth=True))  # depth, no device poses: RGB-D odometry
            messages = receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == FRAMES - 1, timeout_s=180)
    assert not of_type(messages, "error"), of_type(messages, "error")
    lost, back = of_type(messages, "tracking_lost"), of_type(messages, "relocalized")
    assert [m["seq"] for m in lost] == [BLACK] and lost[0]["reason"]
    assert [m["seq"] for m in back] == [BLACK + 1]
    poses = {m["seq"]: np.reshape(m["pose"], (4, 4)) for m in of_type(messages, "pose")}
    assert sorted(poses) == list(range(FRAMES)) and all(np.isfinite(p).all() for p in poses.values())
    np.testing.assert_allclose(poses[BLACK], poses[BLACK - 1])  # held, not a jump


def test_the_sdk_reports_tracking_events(stack) -> None:
    from client.sdk import FlashMonoClient, TrackingEvent
    from client.streaming import WireOptions, open_frames

    frames = list(open_frames(str(ICL_DIR), max_frames=FRAMES, use_gt_depth=True, use_gt_poses=False))
    frames[BLACK].image = np.zeros_like(frames[BLACK].image)
    frames[BLACK].depth = np.zeros_like(frames[BLACK].depth)
    seen = []
    with FlashMonoClient(stack.base_url) as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset="fast")
        summary = client.stream(session.id, frames, wire=WireOptions(send_depth=True, send_pose=False),
                                on_event=lambda e: seen.append(e) if isinstance(e, TrackingEvent) else None)
    # RGB-D keyframes tied to their neighbours solve the graph as they come (`drift_corrected`): not this test's
    kinds = [(e.kind, e.seq) for e in summary.tracking_events if e.kind != "drift_corrected"]
    assert kinds == [("tracking_lost", BLACK), ("relocalized", BLACK + 1)]
    assert [(e.kind, e.seq) for e in seen if e.kind != "drift_corrected"] == kinds
    assert next(e for e in summary.tracking_events if e.kind == "tracking_lost").data["reason"]


def test_a_new_map_after_a_jump_reaches_the_client(stack) -> None:
    """RGB only: the camera jumps to a view the first 20 frames never saw (learned matching cannot find it either
    at this size); the client gets `tracking_lost`, then `new_map` and the new map's `initialized`, the lost and
    waiting frames hold the last pose."""
    frames = icl_frames(71)
    sequence = frames[:20] + frames[40:52]
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS, "preset": "fast"}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            for seq, frame in enumerate(sequence):
                ws.send(frame_message(seq, {**frame, "timestamp": seq / 10.0}))  # no depth, no poses: VO
            messages = receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == len(sequence) - 1,
                                     timeout_s=240)
    assert not of_type(messages, "error"), of_type(messages, "error")
    lost = [m["seq"] for m in of_type(messages, "tracking_lost")]
    new = of_type(messages, "new_map")
    assert 20 in lost and len(new) == 1 and new[0]["seq"] > 20 and new[0]["map"] == 2
    made = [m["seq"] for m in of_type(messages, "initialized") if m["seq"] > new[0]["seq"]]
    assert made, "the new map initialises"
    poses = {m["seq"]: np.reshape(m["pose"], (4, 4)) for m in of_type(messages, "pose")}
    assert all(np.isfinite(p).all() for p in poses.values())
    for seq in range(20, made[0]):
        np.testing.assert_allclose(poses[seq], poses[19])  # lost or waiting: held, never a jump
