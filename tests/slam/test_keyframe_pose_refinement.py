"""`mapping.final_refine_poses`: the final refinement refines the keyframes' cameras with the map, the trajectory
follows (a `poses_refined` revision, each frame with the keyframes around it), and sessions whose device poses are
fixed keep them untouched."""

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
    events = [e for e in refined.finish_events if e.TYPE == "poses_refined"]
    assert len(events) == 1 and events[0].keyframes == 2 and events[0].revision == refined.revision
    assert not [e for e in plain.finish_events if e.TYPE == "poses_refined"]
    before = {i: pose for i, _, pose in plain.trajectory("all")}
    after = {i: pose for i, _, pose in refined.trajectory("all")}
    assert sorted(before) == sorted(after) == list(range(len(frames)))
    shifts = {i: float(np.linalg.norm(after[i][:3, 3] - before[i][:3, 3])) for i in before}
    assert shifts[0] == 0.0  # the oldest keyframe holds the map's frame (and frames 1, 2 follow it)
    assert all(np.isfinite(pose).all() for pose in after.values())
    assert 0.0 < max(shifts.values()) < 0.02, shifts  # small: a refinement, not a new trajectory
    # frame 4, a third of the way from keyframe 3 to keyframe 6, moves with both: about 2/3 of 3's shift and 1/3 of
    # 6's (exactly so for the translations of moves without a turn; these turn by hundredths of a degree)
    move = {i: after[i][:3, 3] - before[i][:3, 3] for i in (3, 4, 6)}
    expected = (2 * move[3] + move[6]) / 3
    assert np.linalg.norm(move[4] - expected) < 0.2 * max(np.linalg.norm(move[3]), np.linalg.norm(move[6]))


def test_fixed_device_poses_are_never_refined(frames) -> None:
    system = _finished(frames, "fixed", True)
    assert not [e for e in system.finish_events if e.TYPE == "poses_refined"]
    for (_, _, pose), frame in zip(system.trajectory("all"), frames):
        np.testing.assert_allclose(pose, frame.pose, atol=1e-9)
