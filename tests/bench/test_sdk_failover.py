"""`python -m bench sdk_failover` (issue 42 point 5): the SDK's default stream into a real stack (Redis, the gateway
under uvicorn, two real SLAM workers), the owning worker SIGKILLed mid-stream and no replacement started: the standby
takes the session over, poses resume, and every frame the SDK saw acked has a pose or a `skipped` answer."""

from __future__ import annotations

import argparse
import asyncio

from bench.live import MINI, load_frames
from bench.sdk_failover import FrameTimes, Observed, failover_session, summarize
from service.launcher import LocalStack

FRAMES, SIZE = 40, (160, 120)


def test_the_loss_check_counts_an_acked_frame_without_an_answer() -> None:
    obs = Observed(frames=[FrameTimes(capture=i / 30, sent=i / 30, pose=1.0 + i) for i in range(4)], start=0.0,
                   kill={"at": 2.5}, acked={0, 1, 2, 3}, skipped=[2], posed=[0, 1, 3])
    assert summarize(obs, {0, 1, 3}, None)["acked_lost"] == 0
    lost = summarize(obs, {0, 3}, None)
    assert lost["acked_lost"] == 1 and lost["lost_seqs"] == [1]
    assert summarize(obs, {0, 1, 2, 3}, None)["answered_twice"] == 1
    assert lost["kill"]["gap_s"] == 0.5 and lost["kill"]["first_pose_seq_after"] == 2


def test_a_standby_worker_resumes_the_sdk_stream_after_the_owner_is_killed() -> None:
    frames, intrinsics = load_frames(str(MINI), SIZE, FRAMES, with_depth=True)
    opts = argparse.Namespace(mode="rgbd", fps=30.0, kill_at=0.33, restart=False, timeout_s=120.0)
    with LocalStack(workers=2, worker_env={"FLASHMONO_LOG_LEVEL": "WARNING"}, worker_nice=10) as stack:
        row = asyncio.run(failover_session(stack, frames, intrinsics, opts))
        alive = sum(w.poll() is None for w in stack.workers)
    kill = row["kill"]
    assert row["failure"] is None and row["status"] == "finished", row
    assert alive == 1, "the owner was killed and no replacement started"
    assert kill is not None and kill["gap_s"] is not None, f"no pose after the kill: {row}"
    assert kill["phases"] is not None and kill["phases"]["worker"] != kill["owner"], "the standby took over"
    assert row["acked"] == FRAMES and row["acked_lost"] == 0, f"acked frames lost: {row['lost_seqs']}"
    assert row["answered_twice"] == 0
    assert row["in_trajectory"] + row["skipped"] == FRAMES
