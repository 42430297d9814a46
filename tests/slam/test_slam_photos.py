"""RGB-only frames through the engine, as photos: frames half a second apart are registered as photos (worker.tracking
.photos), every registered photo a keyframe; photos out of sight of the map are reported lost and then revised into
the trajectory when a later photo places them; frames 1/30 s apart still go to visual odometry; a snapshot taken
before the choice continues with it (real ICL frames, tests/data/icl_mini)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def icl():
    src = open_source(str(DATA), use_gt_depth=False, use_gt_poses=False)
    return list(src), src.intrinsics


def _photos(frames, order: list[int], interval: float = 0.5):
    """The frames of `order` as a photo series: indices 0.., `interval` seconds apart."""
    return [replace(frames[i], index=n, timestamp=n * interval) for n, i in enumerate(order)]


def _config() -> SlamConfig:
    return SlamConfig.preset("rgbd", threaded=False, mapping={"refine_iterations": 1, "final_refine_passes": 0})


def _ate(system: SlamSystem, photos) -> float:
    poses = np.stack([p for _, _, p in system.trajectory()])
    return absolute_trajectory_error(poses, np.stack([f.gt_pose for f in photos]), "sim3").rmse


def test_frames_half_a_second_apart_are_registered_as_photos(icl) -> None:
    frames, intr = icl
    photos = _photos(frames, list(range(0, 41, 2)))
    system = SlamSystem(_config(), intr)
    results = [system.push(f) for f in photos]
    system.finish()
    assert system.mode == "visual_odometry" and system.stats()["pose_strategy"] == "photos"
    assert system.keeps_every_frame  # a live stream skips no photo
    assert all(r.tracked for r in results) and all(np.all(np.isfinite(r.pose)) for r in results)
    assert len(system.trajectory("keyframes")) >= len(photos) - 4  # the photos the first map waited for are not
    assert _ate(system, photos) < 0.02  # metres on a 2 m walk (measured 0.95 cm)
    assert [e.TYPE for e in system.finish_events] == ["poses_refined"]  # every photo adjusted at the end
    system.close()


def test_photos_out_of_sight_are_lost_then_revised_into_the_trajectory(icl) -> None:
    frames, intr = icl
    beyond = list(range(50, 61, 2))
    photos = _photos(frames, list(range(0, 21, 2)) + beyond + list(range(22, 49, 2)))
    system = SlamSystem(_config(), intr)
    results = [system.push(f) for f in photos]
    system.finish()
    lost = [r.index for r in results if not r.tracked]
    assert lost == list(range(11, 11 + len(beyond)))
    late = [e for r in results for e in r.events if e.TYPE == "relocalized" and e.registered_frames]
    assert late and sorted(late[0].registered_frames) == lost and late[0].revision is not None
    assert _ate(system, photos) < 0.03  # the lost photos at their registered poses, not where they were held
    system.close()


def test_frames_of_a_video_still_go_to_visual_odometry(icl) -> None:
    frames, intr = icl
    system = SlamSystem(_config(), intr)
    for f in frames[:6]:
        system.push(f)
    assert system.stats()["pose_strategy"] == "visual_odometry" and not system.keeps_every_frame
    system.close()


def test_a_snapshot_before_the_choice_continues_with_photos(icl) -> None:
    frames, intr = icl
    photos = _photos(frames, list(range(0, 21, 2)))
    straight = SlamSystem(_config(), intr)
    expected = [straight.push(f).pose for f in photos]
    first = SlamSystem(_config(), intr)
    first.push(photos[0])
    restored = SlamSystem.restore(first.snapshot())
    got = [restored.push(f).pose for f in photos[1:]]
    assert restored.stats()["pose_strategy"] == "photos"
    for a, b in zip(got, expected[1:]):
        np.testing.assert_allclose(a, b, atol=1e-6)
    for system in (straight, first, restored):
        system.close()
