"""RGB-D sessions tie each new keyframe to the older keyframes near it by dense alignment (`covisible` pose-graph
edges, worker.loop.keyframe_alignment), on real Kinect frames: TUM fr1/xyz frames 40-87 (tests/data/tum_fr1_xyz_mini,
CC BY 4.0), the camera moving forward and back over a desk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.events import DriftCorrected
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "tum_fr1_xyz_mini"


@pytest.fixture(scope="module")
def frames():
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=False)
    return list(src), src.intrinsics


def _system(intrinsics, neighbours: int = 4) -> SlamSystem:
    config = SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False},
                               loop={"covisible_neighbours": neighbours})
    return SlamSystem(config, intrinsics)


def _run(system: SlamSystem, frames) -> tuple[list, float]:
    results = [system.push(f) for f in frames]
    system.finish()
    poses = np.stack([p for _, _, p in system.trajectory()])
    return results, absolute_trajectory_error(poses, np.stack([f.gt_pose for f in frames]), "se3").rmse


def test_each_keyframe_is_tied_to_its_neighbours_and_the_graph_solved(frames) -> None:
    frames, intrinsics = frames
    with_edges, without = _system(intrinsics), _system(intrinsics, neighbours=0)
    results, ate = _run(with_edges, frames)
    _, ate_without = _run(without, frames)
    edges = with_edges.pose_graph.edges_of_kind("covisible")
    keyframes = sorted(with_edges.pose_graph.nodes)
    assert len(edges) >= len(keyframes) // 2 and all(e.i < e.j for e in edges)
    assert without.pose_graph.edges_of_kind("covisible") == [] and without.loop_stage.alignment is None
    solved = [e for r in results for e in r.events if isinstance(e, DriftCorrected) and e.source == "covisibility"]
    assert solved and all(e.revision is not None for e in solved)
    # The solved graph honours the measured edges: each keyframe pair sits as dense alignment found it
    nodes = with_edges.pose_graph.nodes
    for edge in edges:
        solved = np.linalg.inv(nodes[edge.i]) @ nodes[edge.j]
        assert np.linalg.norm(solved[:3, 3] - edge.relative[:3, 3]) < 0.01, (edge.i, edge.j)
    # 48 frames that odometry already tracks to the motion capture's own agreement with the images (~1 cm): the
    # edges must not cost accuracy (TUM's whole 788 frames: 1.25 -> 1.18 cm, bench/RESULTS.md)
    assert ate < 1.1 * ate_without, (ate, ate_without)
    assert with_edges.stats()["runtime_breakdown"]["keyframe_alignment"]["events"] >= len(keyframes) - 1
    with_edges.close()
    without.close()


def test_a_restored_session_aligns_its_next_keyframes_to_the_ones_before_the_snapshot(frames) -> None:
    frames, intrinsics = frames
    first = _system(intrinsics)
    for frame in frames[:30]:
        first.push(frame)
    before = set(first.loop_stage.alignment.keyframes)
    restored = SlamSystem.restore(first.snapshot())
    first.close()
    assert set(restored.loop_stage.alignment.keyframes) == before and len(before) >= 2
    for frame in frames[30:]:
        restored.push(frame)
    restored.finish()
    later = [e for e in restored.pose_graph.edges_of_kind("covisible") if e.j > max(before)]
    assert later and any(e.i in before for e in later)
    restored.close()


def test_posed_rgbd_ties_keyframes_too_unless_the_device_poses_are_kept_as_they_are() -> None:
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=True)  # the motion capture as the device's poses
    frames = list(src)
    for pose_mode, tied in (("seeded", True), ("fixed", False)):
        config = SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False},
                                   input={"pose_mode": pose_mode})
        system = SlamSystem(config, src.intrinsics)
        for frame in frames:
            system.push(frame)
        system.finish()
        assert system.tracking == "device"
        assert bool(system.pose_graph.edges_of_kind("covisible")) == tied, pose_mode
        if not tied:  # the device's poses, untouched
            for (_, _, pose), frame in zip(system.trajectory(), frames):
                np.testing.assert_allclose(pose, frame.pose, atol=1e-9)
        system.close()
