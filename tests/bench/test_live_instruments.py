"""The measuring instruments of `python -m bench live` and `python -m bench long` (issue 24): the paced pipelined
client against a real stack (Redis, the gateway under uvicorn, a passthrough worker slower than the client, a
queue of 4 frames: backpressure is certain, and frames may be skipped), and the forward-and-back frame order of the
long-session bench."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import numpy as np
import pytest
from live_stack import LiveStack

from bench.live import LiveRun, mode_inputs, pose_source_verdict, summarize
from bench.long_session import ping_pong
from client.streaming import WireOptions, encode_frame_message
from worker.data.frame import Frame

FRAMES, FPS = 40, 30.0


def test_ping_pong_plays_forward_and_back_without_repeating_the_ends() -> None:
    assert list(ping_pong(4, 12)) == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3, 2, 1]
    assert list(ping_pong(2, 5)) == [0, 1, 0, 1, 0]
    with pytest.raises(ValueError):
        list(ping_pong(1, 3))


def _messages() -> list[bytes]:
    wire = WireOptions(send_intrinsics=False, send_pose=True)
    out = []
    for i in range(FRAMES):
        pose = np.eye(4)
        pose[0, 3] = float(i)
        image = np.full((48, 64, 3), (37 * i) % 256, np.uint8)
        out.append(encode_frame_message(Frame(index=i, timestamp=i / FPS, image=image, pose=pose), i, wire))
    return out


def test_live_client_accounts_for_every_frame_under_backpressure() -> None:
    env = {"FLASHMONO_MAX_QUEUE": "4", "FLASHMONO_PASSTHROUGH_DELAY_MS": "60"}
    with LiveStack(workers=1, engine="passthrough", extra_env=env) as stack:
        import httpx

        session_id = httpx.post(f"{stack.url}/v1/sessions", json={"name": "instruments"}).json()["id"]
        run = LiveRun(f"ws://127.0.0.1:{stack.port}/v1/sessions/{session_id}/stream", _messages(), FPS)
        asyncio.run(run.run(timeout_s=120))
        poses = httpx.get(f"{stack.url}/v1/sessions/{session_id}/trajectory").json()["poses"]
    assert run.failure is None
    assert run.rewinds > 0, "a 60 ms worker behind a 4-frame queue must refuse some of 30 frames/s"
    # every frame acked, then exactly one result: a pose, or `skipped` where the worker skips under overload
    assert all(f.acked is not None and (f.pose is None) != (f.skipped is None) and f.poses <= 1 for f in run.frames)
    assert all(f.capture <= f.sent <= (f.pose or f.skipped) for f in run.frames), "a result before its frame"
    assert run.frames[-1].pose is not None, "the newest frame is never skipped"
    args = SimpleNamespace(fps=FPS, mode="rgbd", kill_at=None)
    summary = summarize(run, [], {"status": "finished"}, {int(p["seq"]): np.asarray(p["pose"]).reshape(4, 4)
                                                          for p in poses}, [], args, {})
    assert summary["acked"] == summary["with_pose"] + summary["skipped"] == FRAMES
    assert summary["with_pose"] == len(poses), "the live poses are the trajectory's"
    assert summary["acked_lost"] == 0 and summary["duplicate_poses"] == 0
    assert summary["resends"] > 0
    assert 0 < summary["latency_ms"][50] <= summary["latency_ms"][95] <= summary["latency_ms"][99]
    assert summary["finish_s"] is not None and summary["types"]["finished"] == 1


def test_posed_modes_send_poses_and_report_the_verdict_stall() -> None:
    assert mode_inputs("posed-rgb") == (False, True) and mode_inputs("posed-rgbd") == (True, True)
    assert mode_inputs("rgb") == (False, False) and mode_inputs("rgbd") == (True, False)
    run = LiveRun("ws://unused", [b""] * 3, FPS)
    assert pose_source_verdict(run) is None  # no device poses judged
    for i, log in enumerate(run.frames):
        log.capture, log.pose = float(i), float(i) + (0.5 if i == 1 else 0.02)
    run.events.append((1.5, {"type": "pose_source_chosen", "pose_source": "seeded", "seq": 1, "frames_replayed": 2}))
    verdict = pose_source_verdict(run)
    assert verdict["pose_source"] == "seeded" and verdict["frames_replayed"] == 2 and verdict["seq"] == 1
    assert verdict["latency_ms"] == pytest.approx(500.0)
