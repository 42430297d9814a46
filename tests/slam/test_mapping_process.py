"""Mapping in a process of its own (worker.pipeline.mapping_process): the same map as the mapping thread makes,
tracking that publishes poses while the process is stopped, a process killed mid-session replaced from its
checkpoint with every keyframe in the map, snapshots that restore, and multi-view depth whose loop queries and depth
hints come back from the process."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from live_sessions import live_config, push_all_within

from worker.config import SlamConfig
from worker.data import Frame, open_source
from worker.pipeline.map_jobs import KeyframeJob
from worker.pipeline.mapping_process import MappingProcess
from worker.pipeline.mapping_process import proxy as proxy_module
from worker.pipeline.mapping_stage import MappingStage
from worker.slam import SlamSystem

SIZE = (80, 60)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(Path(__file__).parents[1] / "data" / "icl_mini", max_frames=14, resize=SIZE,
                            use_gt_depth=True))


def process_config(**overrides) -> SlamConfig:
    """`live_config` with mapping in its own process."""
    return live_config(**{**overrides, "mapping": {"process": True, **overrides.get("mapping", {})}})


def keyframe_jobs(frames: list[Frame], count: int) -> list[KeyframeJob]:
    jobs = []
    for i, frame in enumerate(frames[:count]):
        K = frame.intrinsics.matrix()
        image = torch.from_numpy(frame.image.astype(np.float32) / 255.0)
        jobs.append(KeyframeJob(i, np.asarray(frame.gt_pose, np.float64), K, image,
                                depth=torch.from_numpy(frame.depth.astype(np.float32))))
    return jobs


def test_the_process_makes_the_map_the_thread_makes(frames) -> None:
    config = process_config(mapping={"idle_refine": False}, num_threads=1)
    thread = MappingStage(config.mapping, True, config.queue_size, config.device)
    process = MappingProcess(config)
    try:
        assert process.pid is not None and process.pid != os.getpid()
        for stage in (thread, process):
            for job in keyframe_jobs(frames, 4):
                stage.submit(job)
                stage.wait_idle()
        assert process.keyframes_mapped == thread.keyframes_mapped == 4
        assert process.num_gaussians() == thread.num_gaussians() > 0
        K = frames[1].intrinsics.matrix()
        pose = np.asarray(frames[1].gt_pose, np.float64)
        ours, theirs = process.render(pose, K, *SIZE), thread.render(pose, K, *SIZE)
        assert torch.allclose(ours.rgb, theirs.rgb, atol=1e-5) and torch.allclose(ours.depth, theirs.depth, atol=1e-5)
        assert process.to_ply_bytes() == thread.to_ply_bytes()
        assert process.timings.counts["map_merge"] == 4 and process.timings.seconds["map_refine"] > 0
    finally:
        thread.close()
        process.close()
    assert process.num_gaussians() == thread.num_gaussians()  # closed: the map was taken back first
    assert process.render(pose, K, *SIZE).rgb.shape == (SIZE[1], SIZE[0], 3)


def test_tracking_publishes_poses_while_the_mapping_process_is_stopped(frames) -> None:
    system = SlamSystem(process_config(queue_size=64))
    system.push(frames[0])
    pid = system.mapping_stage.pid
    os.kill(pid, signal.SIGSTOP)  # the mapping process can do nothing now
    try:
        results = push_all_within(system, frames[1:])
        assert all(np.all(np.isfinite(r.pose)) for r in results)
        keyframes = sum(r.is_keyframe for r in results)
        assert keyframes >= 4 and system.live_stats()["mapping_lag_keyframes"] >= keyframes
    finally:
        os.kill(pid, signal.SIGCONT)
    system.finish()
    assert system.mapping_stage.pending == 0
    assert system.live_stats()["mapping_lag_keyframes"] == 0
    assert system.stats()["keyframes_mapped"] == keyframes + 1 + (system.last_frame_mapped is not None)
    assert system.num_gaussians > 0
    # both processes' stages in one breakdown: tracking timed here, mapping's reported by its process
    assert system.timings.seconds["frontend_tracking"] > 0 and system.timings.counts["map_merge"] >= keyframes


def test_a_killed_mapping_process_is_replaced_and_no_keyframe_is_lost(frames, monkeypatch) -> None:
    monkeypatch.setattr(proxy_module, "CHECKPOINT_EVERY", 2)  # a checkpoint within the first keyframes
    system = SlamSystem(process_config(queue_size=64))
    first = push_all_within(system, frames[:7])
    system.mapping_stage.wait_idle()
    deadline = time.monotonic() + 30
    while system.mapping_stage.checkpoint.data is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert system.mapping_stage.checkpoint.covers >= 2, "no checkpoint was taken"
    killed = system.mapping_stage.pid
    os.kill(killed, signal.SIGKILL)
    rest = push_all_within(system, frames[7:])
    system.finish()
    results = first + rest
    assert all(np.all(np.isfinite(r.pose)) for r in results)
    stats = system.stats()
    assert stats["mapping_process_restarts"] == 1 and system.mapping_stage.pid != killed
    keyframes = sum(r.is_keyframe for r in results) + (system.last_frame_mapped is not None)
    assert stats["keyframes_mapped"] == keyframes  # every keyframe in the map: none lost, none twice
    assert len(system.mapping_stage.map.keyframe_ids) == keyframes
    rgb, depth = system.render_view(frames[5].gt_pose, frames[5].intrinsics.matrix(), *SIZE)
    assert (depth > 0).mean() > 0.5 and rgb.std() > 5


def test_a_snapshot_of_a_session_mapping_in_a_process_restores_and_continues(frames) -> None:
    system = SlamSystem(process_config(queue_size=64))
    push_all_within(system, frames[:8])
    data = system.snapshot()
    restored = SlamSystem.restore(data)
    try:
        assert isinstance(restored.mapping_stage, MappingProcess)
        assert restored.mapping_stage.pid != system.mapping_stage.pid
        push_all_within(restored, frames[8:])
        restored.finish()
        assert restored.stats()["keyframes_mapped"] >= 5 and restored.num_gaussians > 0
    finally:
        system.close()
        restored.close()


def test_multiview_depth_in_the_process_sends_loop_queries_and_depth_hints_back(frames) -> None:
    posed_rgb = [Frame(f.index, f.timestamp, f.image, intrinsics=f.intrinsics, pose=f.gt_pose) for f in frames]
    system = SlamSystem(process_config(input={"pose_mode": "seeded"}, loop={"enabled": True}))
    push_all_within(system, posed_rgb)
    system.finish()
    stage = system.mapping_stage
    assert system.depth_source == "mvs" and system.with_depth is False
    assert stage.stereo is not None and stage.stereo.recent_hint[1] is not None  # the process's hint came back
    assert stage.keyframes_mapped >= 4 and system.num_gaussians > 0
    assert system.loop_closer is not None and stage._queried  # keyframe loop queries came back after their depth


def test_the_worker_memory_figure_counts_its_mapping_processes() -> None:
    from worker.runtime.memory import descendants, proportional_mb, resident_mb

    process = MappingProcess(process_config())
    try:
        assert process.pid in descendants(os.getpid())  # a child of the fork server, which is ours
        own = resident_mb() - sum(proportional_mb(pid) for pid in descendants(os.getpid()))
        assert proportional_mb(process.pid) > 1
        assert resident_mb() >= own + proportional_mb(process.pid)  # its pages count (shared ones once)
    finally:
        process.close()


def test_a_live_rgb_only_session_keeps_publishing_poses_while_its_mapping_process_is_stalled() -> None:
    source = open_source(str(Path(__file__).parents[1] / "data" / "icl_mini"), use_gt_depth=False,
                         use_gt_poses=False, max_frames=24)
    rgb, intrinsics = list(source), source.intrinsics
    config = SlamConfig.preset("rgbd", mapping={"process": True, "refine_iterations": 1, "final_refine_passes": 0})
    system = SlamSystem(config, intrinsics)
    system.push(rgb[0])
    pid = system.mapping_stage.pid
    os.kill(pid, signal.SIGSTOP)  # multi-view depth, fusion and refinement can do nothing now
    try:
        results = push_all_within(system, rgb[1:])
        assert system.mode == "visual_odometry" and system.depth_source == "mvs"
        assert all(np.all(np.isfinite(r.pose)) for r in results)
        assert sum(r.tracked for r in results) >= len(results) - 2
        assert system.mapping_stage.keyframes_mapped == 0 and system.mapping_stage.pending > 0
    finally:
        os.kill(pid, signal.SIGCONT)
    system.finish()
    assert system.stats()["keyframes_mapped"] >= 3 and system.num_gaussians > 1000


def test_a_mapping_process_that_keeps_dying_fails_the_session_with_a_clear_error(frames, monkeypatch) -> None:
    monkeypatch.setattr(proxy_module, "MAX_RESTARTS", 0)
    system = SlamSystem(process_config(queue_size=64))
    push_all_within(system, frames[:3])
    os.kill(system.mapping_stage.pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while system.mapping_stage._failure is None and time.monotonic() < deadline:
        time.sleep(0.05)
    with pytest.raises(RuntimeError, match="mapping process died"):
        system.push(frames[3])
    system.close()


def test_the_fork_server_is_ready_with_the_engine_imported_when_prestart_returns() -> None:
    from worker.pipeline.mapping_process.launcher import prestart

    assert prestart(timeout_s=120)
