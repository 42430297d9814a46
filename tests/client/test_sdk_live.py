"""The sync and async SDK against a real stack: Redis, the gateway under uvicorn and a worker process. Frames come
from the bundled ICL subset, sent like a phone with depth and device poses.

The worker runs the runtime's passthrough engine with a simulated 150 ms per frame: these tests are about the SDK
and the wire protocol (flow control, backpressure, events, errors), and the SLAM engine's CPU compute would make
them minutes long on 2 cores. The real engine runs behind the same API in tests/e2e (the demo)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import cv2
import numpy as np
import pytest
from live_stack import LiveStack, free_port

from client.async_sdk import AsyncFlashMonoClient
from client.errors import (
    AuthError,
    BadRequestError,
    NotFoundError,
    PermissionDeniedError,
    ServerUnreachableError,
)
from client.models import LoopClosedEvent, PoseEvent
from client.sdk import FlashMonoClient
from client.streaming import WireOptions, open_frames
from worker.data.frame import Frame

KEYS = "streamer=stream,read;reader=read;admin=admin"
ENGINE = "passthrough"  # see the module docstring
PRESET = "test"
RGBD_POSED = WireOptions(send_depth=True, send_pose=True)


@pytest.fixture(scope="module")
def stack():
    # A small server queue so that a greedy client meets backpressure.
    env = {"FLASHMONO_MAX_QUEUE": "3", "FLASHMONO_PASSTHROUGH_DELAY_MS": "150"}
    with LiveStack(workers=1, api_keys=KEYS, engine=ENGINE, extra_env=env) as live:
        yield live


@pytest.fixture(scope="module")
def frames(data_dir_module: Path):
    return list(open_frames(data_dir_module / "icl_mini", max_frames=10, resize=(160, 120), use_gt_poses=True))


@pytest.fixture(scope="module")
def data_dir_module() -> Path:
    return Path(__file__).resolve().parents[1] / "data"


def _camera(frames) -> dict:
    k = frames[0].intrinsics
    return {"width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy}


def test_sync_client_streams_and_fetches_results(stack, frames) -> None:
    events = []
    with FlashMonoClient(stack.url, api_key="streamer") as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset=PRESET, name="sync-walk",
                                        device_id="phone-1", metadata={"app": "tests"})
        assert session.status == "created" and session.name == "sync-walk" and session.device_id == "phone-1"
        summary = client.stream(session.id, frames, on_event=events.append, wire=RGBD_POSED, max_pending=3)
        assert summary.frames_sent == len(frames) == summary.frames_acked
        assert summary.backpressure_retries == 0 and summary.frames_dropped == 0  # max_pending <= server queue
        assert summary.finished_frames == len(frames)
        poses = [e for e in events if isinstance(e, PoseEvent)]
        assert [p.seq for p in poses] == list(range(len(frames)))
        assert [p.timestamp for p in poses] == pytest.approx([f.timestamp for f in frames])
        assert all(p.pose.shape == (4, 4) and np.isfinite(p.pose).all() for p in poses)

        stored = client.get_session(session.id)
        assert stored.status == "finished" and stored.frames_processed == len(frames) and stored.keyframes >= 1
        trajectory = client.trajectory(session.id)
        assert len(trajectory) == len(frames) and trajectory.session_id == session.id
        assert trajectory.positions().shape == (len(frames), 3)
        keyframes = client.trajectory(session.id, "keyframes")
        assert 1 <= len(keyframes) <= len(frames)
        tum = [line for line in client.trajectory_tum(session.id).splitlines() if not line.startswith("#")]
        assert len(tum) == len(frames) and len(tum[0].split()) == 8

        color = client.render_array(session.id, trajectory.poses[-1].pose, **_camera(frames))
        assert color.shape == (120, 160, 3) and color.dtype == np.uint8
        # as the last frame's photo shows it: these frames share one exposure, so nearly the same colours
        captured = client.render_array(session.id, trajectory.poses[-1].pose, exposure_of=trajectory.poses[-1].seq,
                                       **_camera(frames))
        assert captured.shape == color.shape and np.abs(captured.astype(int) - color).mean() < 3
        with pytest.raises(ValueError):
            client.render(session.id, trajectory.poses[-1].pose, exposure_of=-1, **_camera(frames))
        depth = client.render_array(session.id, trajectory.poses[-1].pose, kind="depth", **_camera(frames))
        assert depth.shape == (120, 160) and depth.dtype == np.float32
        ply = client.download_map(session.id)
        assert ply.startswith(b"ply\n")


def test_async_client_yields_live_events_while_streaming(stack, frames) -> None:
    async def scenario() -> tuple[list, object]:
        async with AsyncFlashMonoClient(stack.url, api_key="streamer") as client:
            session = await client.create_session(intrinsics=frames[0].intrinsics, preset=PRESET, name="async")
            received = []
            async with client.open_stream(session.id, wire=RGBD_POSED, max_pending=3) as stream:
                async def consume() -> None:
                    async for event in stream.events():
                        received.append(event)

                consumer = asyncio.create_task(consume())
                for frame in frames[:6]:
                    await stream.send(frame)
                summary = await stream.finish()
                await asyncio.wait_for(consumer, timeout=10)
            listed = [s.id async for s in client.iter_sessions(page_size=1, name="async")]
            assert listed == [session.id]
            return received, summary

    received, summary = asyncio.run(scenario())
    assert [e.seq for e in received if isinstance(e, PoseEvent)] == list(range(6))
    assert all(isinstance(e, (PoseEvent, LoopClosedEvent)) for e in received)
    assert summary.frames_sent == 6


def test_backpressure_is_honoured_without_reordering(stack, frames) -> None:
    with FlashMonoClient(stack.url, api_key="streamer") as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset=PRESET, name="greedy")
        summary = client.stream(session.id, frames, wire=RGBD_POSED, window=16, max_pending=16)
        # The server (queue of 3) refused frames; the client backed off and re-sent them under their seqs: none lost.
        assert summary.backpressure_retries > 0
        assert summary.frames_dropped == 0 and len(summary.poses) == len(frames) == summary.frames_sent
        timestamps = [p.timestamp for p in summary.poses]
        assert timestamps == sorted(timestamps) and len(set(timestamps)) == len(timestamps)
        assert client.get_session(session.id).frames_processed == len(summary.poses)


def test_errors_are_typed_and_carry_the_server_message(stack, frames) -> None:
    with FlashMonoClient(stack.url, api_key="wrong-key") as client:
        with pytest.raises(AuthError) as info:
            client.list_sessions()
        assert info.value.status_code == 401 and info.value.message
    with FlashMonoClient(stack.url, api_key="reader") as reader:
        with pytest.raises(PermissionDeniedError):
            reader.create_session(name="not allowed")
        with pytest.raises(NotFoundError):
            reader.get_session("no-such-session")
    with FlashMonoClient(stack.url, api_key="streamer") as client:
        with pytest.raises(BadRequestError, match="cx|principal"):
            client.create_session(intrinsics={"fx": 100, "fy": 100, "cx": 900, "cy": 60, "width": 160, "height": 120})
        with pytest.raises(ValueError, match="16 values|4x4"):
            client.render("whatever", [1, 2, 3], **_camera(frames))
        with pytest.raises(AuthError):
            FlashMonoClient(stack.url, api_key="wrong-key").stream("any", frames[:1])
        with pytest.raises(NotFoundError):
            client.stream("no-such-session", frames[:1])
    with pytest.raises(ServerUnreachableError, match="cannot reach"):
        FlashMonoClient(f"http://127.0.0.1:{free_port()}").health()


def test_refused_frames_are_reported_and_the_stream_continues(stack, frames) -> None:
    # A square frame without intrinsics cannot belong to the session's 4:3 camera: the gateway refuses it.
    square = Frame(index=1, timestamp=frames[1].timestamp, image=np.zeros((120, 120, 3), np.uint8))
    with FlashMonoClient(stack.url, api_key="streamer") as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset=PRESET, name="mixed")
        summary = client.stream(session.id, [frames[0], square, frames[2]], wire=RGBD_POSED, max_pending=3)
    assert [(e["code"], e["seq"]) for e in summary.errors] == [("bad_intrinsics", 1)]
    assert "aspect ratio" in summary.errors[0]["message"]
    assert [p.seq for p in summary.poses] == [0, 2]


def test_streams_from_a_video_file_and_an_image_folder(stack, frames, tmp_path: Path) -> None:
    video = tmp_path / "walk.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120))
    for frame in frames[:5]:
        writer.write(cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))
    writer.release()
    folder = tmp_path / "images"
    folder.mkdir()
    for i, frame in enumerate(frames[:4]):
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))
    k = frames[0].intrinsics
    options = {"intrinsics": k}  # neither a video nor a folder of images knows its camera
    with FlashMonoClient(stack.url, api_key="streamer") as client:
        for source, count in ((video, 5), (folder, 4)):
            session = client.create_session(intrinsics=k, preset=PRESET, name=source.name)
            summary = client.stream(session.id, str(source), source_options=options, max_pending=3)
            assert [p.seq for p in summary.poses] == list(range(count)), source
            assert client.get_session(session.id).frames_processed == count
