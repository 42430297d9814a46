"""`mapping.final_refine_poses`: the final refinement refines the keyframes' cameras with the map, the trajectory
follows (a `poses_refined` revision), and sessions whose device poses are fixed keep them untouched."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import Frame, open_source
from worker.slam import SlamSystem

SIZE = (80, 60)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(Path(__file__).parents[1] / "data" / "icl_mini", max_frames=7, resize=SIZE,
                            use_gt_poses=True))


def _finished(frames: list[Frame], pose_mode: str, refine_poses: bool) -> SlamSystem:
    system = SlamSystem(SlamConfig.preset(
        "test", input={"pose_mode": pose_mode, "surfel_init": "depth"},
        frontend={"keyframe_every": 3, "keyframe_parallax": 1.0},
        mapping={"refine_keyframes": 1, "refine_iterations": 1, "archived_images": 4, "final_refine_passes": 6,
                 "final_refine_poses": refine_poses}))
    for frame in frames:
        system.push(frame)
    system.finish()
    return system


def test_the_keyframes_cameras_are_refined_and_every_frame_follows(frames) -> None:
    plain, refined = _finished(frames, "prior", False), _finished(frames, "prior", True)
    events = [e for e in refined.finish_events if e["type"] == "poses_refined"]
    assert len(events) == 1 and events[0]["keyframes"] == 2 and events[0]["revision"] == refined.revision
    assert not [e for e in plain.finish_events if e["type"] == "poses_refined"]
    before = {i: pose for i, _, pose in plain.trajectory("all")}
    after = {i: pose for i, _, pose in refined.trajectory("all")}
    assert sorted(before) == sorted(after) == list(range(len(frames)))
    shifts = {i: float(np.linalg.norm(after[i][:3, 3] - before[i][:3, 3])) for i in before}
    assert shifts[0] == 0.0  # the oldest keyframe holds the map's frame (and frames 1, 2 follow it)
    assert all(np.isfinite(pose).all() for pose in after.values())
    assert 0.0 < max(shifts.values()) < 0.02, shifts  # small: a refinement, not a new trajectory
    # a frame keeps its tracked pose relative to its keyframe
    kf_before, kf_after = before[3], after[3]
    np.testing.assert_allclose(np.linalg.inv(kf_after) @ after[4], np.linalg.inv(kf_before) @ before[4], atol=1e-9)


def test_fixed_device_poses_are_never_refined(frames) -> None:
    system = _finished(frames, "fixed", True)
    assert not [e for e in system.finish_events if e["type"] == "poses_refined"]
    for (_, _, pose), frame in zip(system.trajectory("all"), frames):
        np.testing.assert_allclose(pose, frame.pose, atol=1e-9)
