"""Monocular visual odometry on real ICL frames (tests/data/icl_mini, every third frame at 320x240): it tracks,
reports its initialisation, survives black, textureless and blurred frames, a sudden jump and a pure rotation away
from the map (lost, then relocalised, never a NaN), restores from a msgpack snapshot, and runs without intrinsics."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.data.frame import Frame
from worker.eval import absolute_trajectory_error
from worker.tracking.base import TrackingResult
from worker.tracking.visual_odometry import VisualOdometry

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(DATA, use_gt_depth=False, use_gt_poses=False))


def _run(vo: VisualOdometry, frames: list[Frame], calibrated: bool = True) -> list[TrackingResult]:
    results = []
    for frame in frames:
        result = vo.track(frame, frame.intrinsics if calibrated else None)
        assert result.pose.shape == (4, 4) and np.all(np.isfinite(result.pose))
        results.append(result)
    return results


def _with_image(frame: Frame, index: int, image: np.ndarray) -> Frame:
    return Frame(index, index / 10.0, np.ascontiguousarray(image), frame.intrinsics)


def _events(results: list[TrackingResult], kind: str) -> list[dict]:
    return [e for r in results for e in r.events if e.TYPE == kind]


def _trajectory(results: list[TrackingResult]) -> np.ndarray:
    poses = np.stack([r.pose for r in results])
    for event in _events(results, "initialized"):
        for index, pose in event.frames:
            poses[index] = np.asarray(pose)
    return poses


def test_tracks_real_frames_and_reports_initialisation(frames):
    vo = VisualOdometry()
    results = _run(vo, frames[:30])
    init = _events(results, "initialized")
    assert len(init) == 1 and init[0].points >= 60
    first = init[0].frame
    assert first <= 8, "initialisation should wait only a few frames"
    assert all(r.tracked for r in results) and not _events(results, "tracking_lost")
    assert [i for i, _ in init[0].frames] == list(range(first))
    assert all(r.keyframe_hint is False for r in results[:first]) and results[first].keyframe_hint
    keyframes = [r for r in results if r.keyframe_hint]
    assert len(keyframes) >= 3
    depth = keyframes[-1].depth
    assert depth.shape == (240, 320) and (depth > 0).sum() >= 50 and np.all(depth >= 0)
    ate = absolute_trajectory_error(_trajectory(results), np.stack([f.gt_pose for f in frames[:30]]), "sim3")
    assert ate.rmse < 0.05


def test_bad_frames_lose_tracking_then_relocalise(frames):
    vo = VisualOdometry()
    before = _run(vo, frames[:16])
    last_pose = before[-1].pose
    h, w = frames[0].height, frames[0].width
    gray = cv2.cvtColor(frames[16].image, cv2.COLOR_RGB2GRAY)
    bad = [np.zeros((h, w, 3), np.uint8),                                  # lens covered
           np.full((h, w, 3), 128, np.uint8),                              # textureless
           cv2.GaussianBlur(frames[16].image, (0, 0), 8.0),                # motion/defocus blur
           np.repeat(cv2.resize(cv2.resize(gray, (8, 6)), (w, h))[..., None], 3, axis=2)]  # a featureless blob
    lost = _run(vo, [_with_image(frames[16], 100 + n, image) for n, image in enumerate(bad)])
    assert not any(r.tracked for r in lost)
    assert [e.TYPE for e in lost[0].events] == ["tracking_lost"] and lost[0].events[0].reason
    assert all(not r.events for r in lost[1:]), "one loss, reported once"
    assert all(np.array_equal(r.pose, last_pose) and r.keyframe_hint is False for r in lost)
    after = _run(vo, frames[16:22])
    back = _events(after, "relocalized")
    assert len(back) == 1 and after[-1].tracked
    recovered = next(r for r in after if r.events)
    truth_step = np.linalg.norm(frames[16].gt_pose[:3, 3] - frames[15].gt_pose[:3, 3])
    model_step = np.linalg.norm(recovered.pose[:3, 3] - last_pose[:3, 3])
    assert model_step < 5 * max(truth_step, 1e-3) * _scale(before, frames[:16])


def _scale(results: list[TrackingResult], frames: list[Frame]) -> float:
    """Map units per metre, from the Sim(3) alignment of a stretch of tracked frames."""
    ate = absolute_trajectory_error(_trajectory(results), np.stack([f.gt_pose for f in frames]), "sim3")
    return 1.0 / ate.scale


def test_sudden_jump_is_reported_not_followed(frames):
    vo = VisualOdometry()
    before = _run(vo, frames[:16])
    jump = _run(vo, [_with_image(frames[50], 200, frames[50].image)])[0]
    if jump.tracked:  # it may recognise the new place at once, but then it must say so
        assert [e.TYPE for e in jump.events] == ["relocalized"]
    else:
        assert [e.TYPE for e in jump.events] == ["tracking_lost"]
        assert np.array_equal(jump.pose, before[-1].pose)


def test_pure_rotation_away_from_the_map_and_back(frames):
    vo = VisualOdometry()
    _run(vo, frames[:16])
    K = np.array([[262.5, 0, 160], [0, 262.5, 120], [0, 0, 1.0]])
    base = frames[15]
    angles = list(range(4, 84, 4)) + list(range(80, -1, -4))
    views = []
    for n, degrees in enumerate(angles):  # the camera turns in place: the image moves by K R K^-1
        H = K @ cv2.Rodrigues(np.array([0.0, np.radians(degrees), 0.0]))[0] @ np.linalg.inv(K)
        views.append(_with_image(base, 300 + n, cv2.warpPerspective(base.image, H, (base.width, base.height))))
    results = _run(vo, views)
    lost = [n for n, r in enumerate(results) if any(e.TYPE == "tracking_lost" for e in r.events)]
    found = [n for n, r in enumerate(results) if any(e.TYPE == "relocalized" for e in r.events)]
    assert lost and found and lost[0] < found[-1]
    assert results[-1].tracked
    # Back at the start view: the recovered pose is the base frame's pose again (rotation only, no drift away).
    end = results[-1].pose
    start = vo_pose_of(frames[:16])
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(end[:3, :3] @ start[:3, :3].T)[0])) < 3.0


def vo_pose_of(frames: list[Frame]) -> np.ndarray:
    """The pose a fresh VO gives the last of `frames` (VO is deterministic)."""
    return _run(VisualOdometry(), frames)[-1].pose


def test_snapshot_round_trip_continues_identically(frames):
    vo = VisualOdometry()
    _run(vo, frames[:14])
    restored = VisualOdometry()
    restored.load_state_dict(unpack(pack(vo.state_dict())))
    a = _run(vo, frames[14:20])
    b = _run(restored, frames[14:20])
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x.pose, y.pose, atol=1e-9)
        assert x.keyframe_hint == y.keyframe_hint
    state = vo.state_dict()
    assert len(state["map"]["keyframes"]) <= vo.config.window + vo.config.fixed_keyframes


def test_state_of_another_version_is_refused():
    with pytest.raises(ValueError, match="version"):
        VisualOdometry().load_state_dict({"version": 999})


def test_runs_without_intrinsics(frames):
    vo = VisualOdometry()
    bare = [Frame(f.index, f.timestamp, f.image) for f in frames[:20]]
    results = _run(vo, bare, calibrated=False)
    k = vo.estimated_intrinsics
    assert k is not None and (k.width, k.height) == (320, 240) and 0.3 * 320 < k.fx < 3 * 320
    assert _events(results, "initialized") and sum(r.tracked for r in results) == 20


def test_a_frame_of_another_size_is_refused_and_nothing_is_lost(frames):
    vo = VisualOdometry()
    _run(vo, frames[:12])
    small = Frame(12, 1.2, cv2.resize(frames[12].image, (160, 120)))
    with pytest.raises(ValueError, match="320x240"):
        vo.track(small, None)
    result = vo.track(frames[12], frames[12].intrinsics)
    assert result.tracked and not result.events
