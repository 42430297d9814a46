"""The colour/depth misregistration detector on real Kinect v1 frames (tests/data/tum_fr1_rpy_mini: TUM fr1/rpy,
depth registered to colour by the OpenNI driver). A known shift of the real depth moves the detector's estimate by
that shift, and these registered frames are not flagged (their best shift, (-1, -1) px, is within a registered
sensor's tolerance)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.data.registration import MisregistrationDetector
from worker.pipeline.depth_registration import DepthRegistration

DATA = Path(__file__).parents[1] / "data" / "tum_fr1_rpy_mini"


@pytest.fixture(scope="module")
def frames():
    return list(open_source(DATA, use_gt_depth=True))


def _shift(frames, dx: int = 0, dy: int = 0) -> tuple[int, int]:
    detector = MisregistrationDetector(frames=len(frames), max_shift=10)
    for f in frames:
        detector.add(f.image, np.roll(f.depth, (dy, dx), axis=(0, 1)))
    verdict = detector.verdict()
    assert verdict is not None and verdict.edges > 1000  # a desk scene: plenty of depth edges
    return verdict.shift


@pytest.mark.parametrize("dx, dy", [(6, 0), (-6, 0), (0, 6), (0, -6), (4, -4)])
def test_a_known_shift_of_real_depth_moves_the_estimate_by_that_shift(frames, dx: int, dy: int) -> None:
    base = _shift(frames)
    moved = _shift(frames, dx, dy)
    # depth content moved by (dx, dy) is found best (-dx, -dy) further: within a pixel (Kinect depth edges are ragged)
    assert abs(moved[0] - base[0] + dx) <= 1 and abs(moved[1] - base[1] + dy) <= 1, (base, moved)


def test_registered_real_kinect_frames_are_not_flagged(frames) -> None:
    config = SlamConfig.preset("rgbd")
    registration = DepthRegistration(None, config.input.detect_misregistration_frames)
    events = [event for f in frames for event in registration.apply(f, f.intrinsics)[1]]
    assert registration.checked
    assert not [e for e in events if e.TYPE == "depth_misregistered"], events
