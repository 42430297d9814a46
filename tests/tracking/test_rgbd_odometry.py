"""RGB-D odometry on real ICL frames (tests/data/icl_mini: every third frame at 320x240 with depth): dense alignment
against the pseudo ground truth, the whole clip tracked, bad input (black frames, zero depth, a jump) reported as
`tracking_lost` without a jump or a NaN, recovery when the view returns, and snapshot/restore."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.data.frame import Frame
from worker.eval import absolute_trajectory_error
from worker.tracking.dense_alignment import align, build_pyramid
from worker.tracking.rgbd_odometry import RgbdOdometry, grey_of

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def sequence():
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=False)
    return list(src), src.intrinsics


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_alignment_recovers_the_relative_pose_of_two_real_frames(sequence) -> None:
    frames, intr = sequence
    K = intr.matrix().numpy().astype(np.float64)
    a, b = frames[4], frames[6]  # six original frames apart: about 12 cm and a few degrees
    truth = np.linalg.inv(b.gt_pose) @ a.gt_pose
    pa = build_pyramid(grey_of(a.image), a.depth, K, 3)
    pb = build_pyramid(grey_of(b.image), b.depth, K, 3)
    result = align(pa, pb, np.eye(4))
    error = np.linalg.inv(truth) @ result.T
    assert result.ok and result.overlap > 0.7
    assert np.linalg.norm(truth[:3, 3]) > 0.05  # the frames did move
    assert np.linalg.norm(error[:3, 3]) < 0.01 and _angle_deg(error[:3, :3]) < 0.5


def test_odometry_tracks_the_whole_clip(sequence) -> None:
    frames, intr = sequence
    odometry = RgbdOdometry()
    results = [odometry.track(f, intr) for f in frames]
    assert all(r.tracked for r in results) and not any(r.events for r in results)
    est = np.stack([r.pose for r in results])
    gt = np.stack([f.gt_pose for f in frames])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    ate = absolute_trajectory_error(est, gt, "se3").rmse
    assert path > 1.0 and ate < 0.03, (path, ate)


def _copy(frame: Frame, **changes) -> Frame:
    fields = {"index": frame.index, "timestamp": frame.timestamp, "image": frame.image, "intrinsics":
              frame.intrinsics, "depth": frame.depth, "gt_pose": frame.gt_pose}
    return Frame(**{**fields, **changes})


@pytest.mark.parametrize("damage", ["black", "zero_depth", "nan_depth"])
def test_bad_frames_are_reported_lost_and_tracking_recovers(sequence, damage) -> None:
    frames, intr = sequence
    odometry = RgbdOdometry()
    for f in frames[:5]:
        last = odometry.track(f, intr)
    broken = {"black": {"image": np.zeros_like(frames[5].image), "depth": np.zeros_like(frames[5].depth)},
              "zero_depth": {"depth": np.zeros_like(frames[5].depth)},
              "nan_depth": {"depth": np.full_like(frames[5].depth, np.nan)}}[damage]
    lost = odometry.track(_copy(frames[5], **broken), intr)
    assert not lost.tracked and lost.keyframe_hint is False
    assert [e.TYPE for e in lost.events] == ["tracking_lost"] and lost.events[0].reason
    np.testing.assert_array_equal(lost.pose, last.pose)  # no jump while lost
    again = odometry.track(frames[6], intr)
    assert again.tracked and [e.TYPE for e in again.events] == ["relocalized"]
    error = np.linalg.inv(np.linalg.inv(frames[0].gt_pose) @ frames[6].gt_pose) @ again.pose
    assert np.linalg.norm(error[:3, 3]) < 0.03


def test_a_jump_to_another_view_is_never_a_silent_wrong_pose(sequence) -> None:
    frames, intr = sequence
    odometry = RgbdOdometry()
    for f in frames[:4]:
        odometry.track(f, intr)
    far = frames[40]  # about 2 m along the path, looking elsewhere
    result = odometry.track(far, intr)
    truth = np.linalg.inv(frames[0].gt_pose) @ far.gt_pose
    if result.tracked:
        assert np.linalg.norm(result.pose[:3, 3] - truth[:3, 3]) < 0.05
    else:
        assert result.events[0].TYPE == "tracking_lost"
    assert np.all(np.isfinite(result.pose))


def test_snapshot_and_restore_continue_exactly(sequence) -> None:
    frames, intr = sequence
    straight = RgbdOdometry()
    expected = [straight.track(f, intr).pose for f in frames[:12]]
    first = RgbdOdometry()
    for f in frames[:7]:
        first.track(f, intr)
    restored = RgbdOdometry()
    restored.load_state_dict(unpack(pack(first.state_dict())))
    continued = [restored.track(f, intr).pose for f in frames[7:12]]
    for got, want in zip(continued, expected[7:]):
        assert np.allclose(got, want, atol=2e-3)


def test_relocalization_after_a_jump_back_to_a_seen_view(sequence) -> None:
    frames, intr = sequence
    odometry = RgbdOdometry()
    for f in frames[:30]:  # well along the path (a metre): several reference keyframes
        odometry.track(f, intr)
    lost = odometry.track(_copy(frames[30], image=np.zeros_like(frames[30].image),
                                depth=np.zeros_like(frames[30].depth)), intr)
    assert not lost.tracked
    back = odometry.track(frames[8], intr)  # back where it was at frame 8, 30 cm from the last pose
    truth = np.linalg.inv(frames[0].gt_pose) @ frames[8].gt_pose
    assert np.linalg.norm(lost.pose[:3, 3] - truth[:3, 3]) > 0.25
    assert back.tracked and back.events[0].TYPE == "relocalized"
    assert np.linalg.norm(back.pose[:3, 3] - truth[:3, 3]) < 0.03
