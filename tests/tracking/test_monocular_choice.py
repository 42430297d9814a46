"""RGB-only sessions choose between visual odometry and photo registration from their first three frames' timing
(worker.tracking.monocular_choice), on real ICL frames (tests/data/icl_mini)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.tracking.monocular_choice import MonocularChoice
from worker.tracking.photos import PhotoRegistration
from worker.tracking.visual_odometry import VisualOdometry

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def frames():
    return list(open_source(str(DATA), use_gt_depth=False, max_frames=8))


def _choice() -> MonocularChoice:
    return MonocularChoice(VisualOdometry, PhotoRegistration, 0.4)


def _timed(frames, times: list[float]):
    return [replace(f, timestamp=t) for f, t in zip(frames, times)]


@pytest.mark.parametrize("times, chosen", [([0.0, 0.5, 1.0], "photos"), ([0.0, 1.0, 1.2], "visual_odometry"),
                                           ([0.0, 0.2, 1.0], "visual_odometry"),
                                           ([0.0, 1 / 30, 2 / 30], "visual_odometry")])
def test_both_first_steps_must_be_long_for_photos(frames, times, chosen) -> None:
    choice = _choice()
    timed = _timed(frames, times)
    results = [choice.track(f, f.intrinsics) for f in timed[:2]]
    assert choice.chosen is None and choice.keeps_every_frame  # a live stream skips none while it decides
    results.append(choice.track(timed[2], timed[2].intrinsics))
    assert choice.chosen == chosen and choice.name == chosen
    assert choice.keeps_every_frame == (chosen == "photos")
    assert isinstance(choice.source, PhotoRegistration if chosen == "photos" else VisualOdometry)
    assert all(np.all(np.isfinite(r.pose)) for r in results)
    assert results[0].keyframe_hint is False and results[1].keyframe_hint is False  # placeholders while deciding


def test_frames_without_intrinsics_are_video_at_once(frames) -> None:
    choice = _choice()
    result = choice.track(_timed(frames, [0.0])[0], None)
    assert choice.chosen == "visual_odometry" and isinstance(choice.source, VisualOdometry)
    assert result.events  # the odometry's own answer to the first frame, not a placeholder
    assert choice.estimated_intrinsics is choice.source.estimated_intrinsics  # what the engine asks reaches it


def test_a_snapshot_of_visual_odometry_alone_continues_as_video(frames) -> None:
    odometry = VisualOdometry()
    expected = [odometry.track(f, f.intrinsics).pose for f in frames]
    before = VisualOdometry()  # a session snapshot of a version whose RGB-only pose source was the odometry itself
    for f in frames[:4]:
        before.track(f, f.intrinsics)
    choice = _choice()
    choice.load_state_dict(unpack(pack(before.state_dict())))
    assert choice.chosen == "visual_odometry" and not choice.keeps_every_frame
    got = [choice.track(f, f.intrinsics).pose for f in frames[4:]]
    for a, b in zip(got, expected[4:]):
        np.testing.assert_allclose(a, b, atol=1e-9)
