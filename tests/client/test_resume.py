"""SDK resume: the gateway is killed (SIGKILL) and started again mid-stream; the SDK re-opens the stream and goes
on at the next unacknowledged seq, with no frame lost or renumbered. A stream opened again on a session continues
after its last seq, and a server that stays away ends the stream within seconds with a clear error."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from client.async_sdk import AsyncFlashMonoClient
from client.errors import ServerUnreachableError
from client.streaming import WireOptions
from service.launcher import LocalStack, start_gateway_process
from worker.data.frame import Frame

WORKER_ENV = {"FLASHMONO_ENGINE": "passthrough", "FLASHMONO_LEASE_TTL_MS": "4000", "FLASHMONO_SNAPSHOT_EVERY": "2",
              "FLASHMONO_PASSTHROUGH_DELAY_MS": "15"}
FRAMES = 40
WIRE = WireOptions(send_pose=True, send_intrinsics=False)


def frame(index: int) -> Frame:
    """A small frame whose pose prior encodes its index (x translation): the passthrough engine echoes it."""
    pose = np.eye(4)
    pose[0, 3] = float(index)
    image = np.full((48, 64, 3), (index * 5) % 256, np.uint8)
    return Frame(index=index, timestamp=index / 30.0, image=image, pose=pose)


def restart_gateway(stack: LocalStack, down_s: float) -> threading.Thread:
    stack.gateway.kill()
    stack.gateway.wait()

    def start() -> None:
        time.sleep(down_s)
        stack.gateway = start_gateway_process(stack.redis_url, stack.host, stack.port)

    thread = threading.Thread(target=start)
    thread.start()
    return thread


@pytest.fixture(scope="module")
def stack():
    with LocalStack(workers=1, worker_env=WORKER_ENV) as local:
        yield local


@pytest.fixture(autouse=True)
def _gateway_up(stack):
    """Each test starts with a serving gateway (some kill it)."""
    if stack.gateway.poll() is not None:
        stack.gateway = start_gateway_process(stack.redis_url, stack.host, stack.port)
    stack.wait_ready(60)


def test_stream_survives_a_gateway_restart_without_loss_or_renumbering(stack):
    async def scenario():
        async with AsyncFlashMonoClient(stack.base_url) as client:
            session = await client.create_session(name="resume", skip_frames=False)
            restarter = None

            def frames():
                nonlocal restarter
                for i in range(FRAMES):
                    if i == 15:
                        restarter = restart_gateway(stack, down_s=1.5)
                    yield frame(i)

            summary = await client.stream(session.id, frames(), wire=WIRE, reconnect_s=30)
            restarter.join()
            trajectory = await client.trajectory(session.id)
            return summary, trajectory, await client.get_session(session.id)

    summary, trajectory, session = asyncio.run(scenario())
    assert summary.reconnects >= 1
    assert [p.seq for p in trajectory.poses] == list(range(FRAMES))
    assert all(p.pose[0, 3] == p.seq for p in trajectory.poses)  # each pose is its own frame's: no renumbering
    assert sorted(e.seq for e in summary.poses) == list(range(FRAMES))  # every result reported, once
    assert session.status == "finished" and session.frames_received == session.frames_processed == FRAMES


def test_a_new_stream_on_a_session_continues_after_its_last_seq(stack):
    async def scenario():
        async with AsyncFlashMonoClient(stack.base_url) as client:
            session = await client.create_session(name="continue", skip_frames=False)
            async with client.open_stream(session.id, wire=WIRE) as first:
                for i in range(5):
                    await first.send(frame(i))
                while first.flow.in_flight:  # every frame acknowledged (queued) before the app goes away
                    await asyncio.sleep(0.02)
            # the camera goes on: a fresh stream object, as after an app restart
            async with client.open_stream(session.id, wire=WIRE) as second:
                for i in range(5, 10):
                    await second.send(frame(i))
                summary = await second.finish()
            return summary, await client.trajectory(session.id)

    summary, trajectory = asyncio.run(scenario())
    assert summary.errors == []
    assert [p.seq for p in trajectory.poses] == list(range(10))
    assert all(p.pose[0, 3] == p.seq for p in trajectory.poses)


def test_an_unreachable_server_ends_the_stream_within_seconds(stack):
    async def scenario():
        async with AsyncFlashMonoClient(stack.base_url) as client:
            session = await client.create_session(name="gone", skip_frames=False)
            async with client.open_stream(session.id, wire=WIRE, reconnect_s=3) as stream:
                await stream.send(frame(0))
                stack.gateway.kill()
                stack.gateway.wait()
                t0 = time.monotonic()
                with pytest.raises(ServerUnreachableError, match="could not reconnect within 3 s"):
                    for i in range(1, 100):
                        await stream.send(frame(i))
                    await stream.finish()
                return time.monotonic() - t0

    assert 3 <= asyncio.run(scenario()) < 15
