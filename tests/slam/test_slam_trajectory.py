"""Trajectory bookkeeping: frames follow their keyframe through pose-graph updates; revisions count rewrites."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worker.geometry import make_sim3, so3_exp
from worker.pipeline.keyframes import MotionKeyframeSelector
from worker.pipeline.trajectory import Trajectory


def pose(x: float, yaw: float = 0.0, s: float = 1.0) -> np.ndarray:
    R = so3_exp(torch.tensor([0.0, yaw, 0.0], dtype=torch.float64))
    return make_sim3(R, torch.tensor([x, 0.0, 0.0], dtype=torch.float64), s).numpy()


def test_frames_move_rigidly_with_their_keyframe() -> None:
    traj = Trajectory()
    traj.add_keyframe(0, pose(0.0))
    assert np.allclose(traj.add_frame(0, 0.0, 0, pose(0.0), True, 0), pose(0.0))
    assert np.allclose(traj.add_frame(1, 0.1, 0, pose(0.1, 0.05), False, 0), pose(0.1, 0.05))
    traj.add_keyframe(2, pose(0.2), reference=0)
    traj.add_frame(2, 0.2, 2, pose(0.2), True, 0)
    correction = pose(0.5, 0.3, 1.2)
    revision = traj.update_keyframes({0: correction @ pose(0.0), 2: correction @ pose(0.2)})
    assert revision == traj.revision == 1
    poses = dict((i, p) for i, _, p in traj.listing("all"))
    assert np.allclose(poses[1], correction @ pose(0.1, 0.05))  # kept its pose relative to keyframe 0
    assert [i for i, _, _ in traj.listing("keyframes")] == [0, 2]
    # a keyframe added after the correction starts from the corrected trajectory, not the raw odometry
    new = traj.add_keyframe(3, pose(0.3), reference=2)
    assert np.allclose(new, correction @ pose(0.3))


def test_state_dict_round_trip_and_order_checks() -> None:
    traj = Trajectory()
    traj.add_keyframe(0, pose(0.0))
    traj.add_frame(0, 0.0, 0, pose(0.0), True, 0)
    traj.add_frame(1, 0.1, 0, pose(0.1), False, 0)
    other = Trajectory()
    other.load_state_dict(traj.state_dict())
    assert [(i, t) for i, t, _ in other.listing()] == [(0, 0.0), (1, 0.1)]
    assert np.allclose(other.listing()[1][2], pose(0.1))
    with pytest.raises(ValueError, match="not after"):
        other.add_frame(1, 0.2, 0, pose(0.2), False, 0)
    with pytest.raises(ValueError, match="'all' or 'keyframes'"):
        other.listing("some")


def test_a_world_moved_before_the_first_keyframe_places_it_and_survives_a_snapshot() -> None:
    """A stored map's anchoring can come before the first keyframe (device poses still being judged): frames
    tracked meanwhile and the first keyframe come out in the moved world."""
    traj = Trajectory()
    move = pose(1.0, 0.4)
    traj.move_world(move)
    assert np.allclose(traj.provisional(pose(0.1)), move @ pose(0.1))
    restored = Trajectory()
    restored.load_state_dict(traj.state_dict())
    assert np.allclose(restored.add_keyframe(0, pose(0.2)), move @ pose(0.2))
    assert np.allclose(restored.add_keyframe(1, pose(0.3), reference=0), move @ pose(0.3))


def test_motion_keyframe_selector() -> None:
    sel = MotionKeyframeSelector(every=5, translation=0.2, rotation_deg=15.0)
    flags = [sel.is_keyframe(pose(0.01 * k)) for k in range(12)]
    assert flags == [True, False, False, False, False, True, False, False, False, False, True, False]
    sel = MotionKeyframeSelector(every=100, translation=0.2, rotation_deg=15.0)
    assert [sel.is_keyframe(pose(x)) for x in (0.0, 0.1, 0.25, 0.3)] == [True, False, True, False]
    assert sel.is_keyframe(pose(0.3, yaw=0.3))  # 17 degrees


def test_frames_a_new_map_posed_later_move_with_its_first_keyframe() -> None:
    """Frames lost before a new map began (held at the old map's last pose) are posed by the new map's
    initialisation and tied to its first keyframe: a join that moves the new map moves them, not the old map."""
    traj = Trajectory()
    traj.add_keyframe(0, pose(0.0))
    traj.add_frame(0, 0.0, 0, pose(0.0), True, 0)
    for i in (1, 2, 3):  # lost: the last pose held, tied to the old map's keyframe
        traj.add_frame(i, 0.1 * i, 0, pose(0.0), False, 0)
    traj.add_keyframe(4, pose(0.4), reference=0)
    traj.add_frame(4, 0.4, 4, pose(0.4), True, 1)
    revision = traj.revise_frames({2: pose(0.2, 0.1), 3: pose(0.3, 0.1)}, keyframe=4, submap_id=1)
    assert revision == traj.revision
    poses = dict((i, p) for i, _, p in traj.listing("all"))
    assert np.allclose(poses[2], pose(0.2, 0.1)) and np.allclose(poses[1], pose(0.0))
    join = pose(0.7, -0.2, 1.5)  # the new map moved into the old one's world and scale
    traj.update_keyframes({4: join @ pose(0.4)})
    poses = dict((i, p) for i, _, p in traj.listing("all"))
    assert np.allclose(poses[2], join @ pose(0.2, 0.1)) and np.allclose(poses[3], join @ pose(0.3, 0.1))
    assert np.allclose(poses[1], pose(0.0)) and np.allclose(poses[0], pose(0.0))  # the old map's stay
    records = {r.index: r for r in traj.frames}
    assert records[2].keyframe == 4 and records[2].submap_id == 1 and records[1].submap_id == 0


def test_frames_between_two_moved_keyframes_move_with_both() -> None:
    """spread_keyframe_moves: a frame 1/4 of the way from keyframe 0 to keyframe 4 takes 3/4 of keyframe 0's move
    and 1/4 of keyframe 4's; frames after the last keyframe, or between keyframes that moved alike, stay rigid; the
    sealed chunks that changed get a new version."""
    traj = Trajectory(chunk_frames=2)
    for index in range(7):
        if index in (0, 4):
            traj.add_keyframe(index, pose(0.1 * index), reference=None if index == 0 else 0)
        traj.add_frame(index, 0.1 * index, 0 if index < 4 else 4, pose(0.1 * index, 0.01 * index), index in (0, 4),
                       0)
    old = {k: p.copy() for k, p in traj.keyframe_poses.items()}
    before = {i: p for i, _, p in traj.listing("all")}
    shift = pose(0.0, 0.0)
    shift[:3, 3] = [0.0, 0.04, 0.0]  # keyframe 4 moves 4 cm up; keyframe 0 stays
    traj.update_keyframes({4: shift @ old[4]})
    revision = traj.spread_keyframe_moves(old)
    after = {i: p for i, _, p in traj.listing("all")}
    assert revision == traj.revision == 2
    for index in (1, 2, 3):
        np.testing.assert_allclose(after[index][:3, 3] - before[index][:3, 3], [0.0, 0.01 * index, 0.0], atol=1e-12)
        np.testing.assert_allclose(after[index][:3, :3], before[index][:3, :3], atol=1e-12)
    for index in (5, 6):  # after the last keyframe: rigidly with it
        np.testing.assert_allclose(after[index], shift @ before[index], atol=1e-12)
    assert traj.chunk_revisions == {0: 1, 1: 1}  # frames 1 and 2, 3 sit in sealed chunks 0 and 1
    assert traj.spread_keyframe_moves(traj.keyframe_poses) == 3  # nothing moved: nothing changes
    assert {i: p for i, _, p in traj.listing("all")}.keys() == after.keys()


def test_frames_measured_against_an_earlier_keyframe_are_placed_on_it() -> None:
    traj = Trajectory()
    traj.add_keyframe(0, pose(0.0))
    traj.add_frame(0, 0.0, 0, pose(0.0), True, 0)
    traj.add_keyframe(5, pose(0.5), reference=0)
    traj.add_frame(5, 0.5, 5, pose(0.5), True, 0)
    # the odometry has the frame at 0.6 (drifted); measured against keyframe 0, come back to, it is at 0.58
    traj.add_frame(6, 0.6, 5, pose(0.6), False, 0, anchor=(0, pose(0.58)))
    traj.add_frame(7, 0.7, 5, pose(0.7), False, 0)
    traj.update_keyframes({5: pose(0.52)})  # the graph moved keyframe 5, not 0
    revision = traj.revision
    assert np.allclose(traj.pose_at(6), pose(0.52) @ np.linalg.inv(pose(0.5)) @ pose(0.6))  # follows keyframe 5
    assert traj.anchor_frames() == 1 and traj.revision == revision + 1
    assert np.allclose(traj.pose_at(6), pose(0.58))
    assert np.allclose(traj.pose_at(7), pose(0.52) @ np.linalg.inv(pose(0.5)) @ pose(0.7))  # not anchored
    restored = Trajectory()
    restored.load_state_dict(traj.state_dict())
    assert [r.anchor for r in restored.frames] == [-1, -1, 0, -1]
    restored.update_keyframes({0: pose(0.01)})
    assert restored.anchor_frames() == 1 and np.allclose(restored.pose_at(6), pose(0.01) @ pose(0.58))
    # a state written before anchors loads with none
    old = {k: v for k, v in traj.state_dict().items() if k not in ("anchor", "anchored")}
    before = Trajectory()
    before.load_state_dict(old)
    assert before.anchor_frames() == 0 and np.allclose(before.pose_at(6), traj.pose_at(6))


def test_source_corrections_move_every_frame_from_its_tracked_pose() -> None:
    traj = Trajectory()
    traj.add_keyframe(0, pose(0.0))
    for i in range(15):
        if i == 10:
            traj.add_keyframe(10, pose(1.0), reference=0)
        traj.add_frame(i, i / 30, 0 if i < 10 else 10, pose(i / 10), i in (0, 10), 0)
    traj.update_keyframes({0: pose(0.0, 0.2), 10: pose(1.0, 0.2)})  # a loop correction the source's replaces
    shift = pose(0.4)
    placed = traj.source_corrected_poses({2: np.eye(4), 12: shift})  # the source's own keyframes
    assert sorted(placed) == list(range(15))
    assert np.allclose(placed[0], pose(0.0)) and np.allclose(placed[2], pose(0.2))  # before and on the first
    assert np.allclose(placed[7], pose(0.7 + 0.2))  # halfway between the two: half the move
    assert np.allclose(placed[14], shift @ pose(1.4))  # after the last: its move
    assert traj.source_corrected_poses({}) == {}
