"""The live path makes the same pose-source choice as an offline run: posed RGB frames (no depth) streamed to a real
stack (gateway, a worker with the SLAM engine, Redis) in the default pose_mode; exact ICL poses get a
`pose_source_chosen` message saying `prior`, the same poses with every position off by a fifth of a frame's step one
saying `seeded` (and a warning in the session record), within the first 30 frames, and every pose stays finite. The
frames are sent at once to a live session (skip_frames): none before the verdict is skipped (the triples need them
all), so the verdict is the one an offline run makes."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from service_helpers import ICL_DIR, ICL_INTRINSICS, frame_message, icl_frames, of_type, receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack

FRAMES = 24


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_TORCH_THREADS": "1", "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=env) as running:
        yield running


def _noisy(frames: list[dict]) -> list[dict]:
    positions = np.stack([np.reshape(f["pose"], (4, 4))[:3, 3] for f in frames])
    step = float(np.median(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
    rng = np.random.default_rng(0)
    out = []
    for frame in frames:
        pose = np.reshape(frame["pose"], (4, 4)).copy()
        pose[:3, 3] += 0.2 * step * rng.standard_normal(3)
        out.append({**frame, "pose": pose.reshape(-1).tolist()})
    return out


@pytest.mark.parametrize("noisy, expected", [(False, "prior"), (True, "seeded")])
def test_the_stream_is_told_which_pose_source_the_device_poses_earned(stack, noisy, expected) -> None:
    frames = icl_frames(FRAMES)
    frames = _noisy(frames) if noisy else frames
    with httpx.Client(base_url=stack.base_url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"intrinsics": ICL_INTRINSICS, "preset": "fast",
                                             "skip_frames": True}).json()["id"]
        with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
            for seq, frame in enumerate(frames):
                ws.send(frame_message(seq, frame, with_pose=True))
            messages = receive_until(ws, lambda m: m["type"] in ("pose", "skipped") and m["seq"] == FRAMES - 1,
                                     timeout_s=180)
        warnings = api.get(f"/v1/sessions/{sid}").json()["warnings"]
    assert not of_type(messages, "error"), of_type(messages, "error")
    [chosen] = of_type(messages, "pose_source_chosen")
    assert chosen["pose_source"] == expected and chosen["seq"] <= 20 and chosen["triples"] >= 1
    assert (chosen["ratio"] > chosen["max_ratio"]) == noisy
    # the verdict's replay revised the trajectory: its message says so, and no loop closure is announced for it
    assert chosen["frames_replayed"] == chosen["seq"] + 1 and chosen["revision"] >= 1
    assert not [m for m in of_type(messages, "loop_closed") if m["revision"] == chosen["revision"]]
    assert not [m for m in of_type(messages, "skipped") if m["seq"] <= chosen["seq"]]
    assert (warnings == [chosen["reason"]]) if noisy else warnings == []
    poses = [np.reshape(m["pose"], (4, 4)) for m in of_type(messages, "pose")]
    assert len(poses) + len(of_type(messages, "skipped")) == FRAMES and all(np.isfinite(p).all() for p in poses)


def test_the_sdk_reports_the_verdict_as_an_input_event(stack) -> None:
    from client.sdk import FlashMonoClient, InputEvent
    from client.streaming import WireOptions, open_frames

    frames = list(open_frames(str(ICL_DIR), max_frames=FRAMES, use_gt_depth=False, use_gt_poses=True))
    seen = []
    with FlashMonoClient(stack.base_url) as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset="fast")
        summary = client.stream(session.id, frames, wire=WireOptions(send_depth=False, send_pose=True),
                                on_event=lambda e: seen.append(e) if isinstance(e, InputEvent) else None)
    [chosen] = [e for e in summary.input_events if e.kind == "pose_source_chosen"]
    assert chosen.data["pose_source"] == "prior" and chosen.data["frames_replayed"] == chosen.seq + 1
    assert seen == summary.input_events
    # the poses after the verdict carry its revision; no loop closure is reported for it
    assert all(p.revision >= chosen.data["revision"] for p in summary.poses if p.seq > chosen.seq)
    assert not [e for e in summary.loop_closures if e.revision == chosen.data["revision"]]
