"""Keyframe selection skips a blurred frame when a sharper one follows (worker.pipeline.keyframes)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data.synthetic import make_sequence
from worker.pipeline.keyframes import MotionKeyframeSelector, sharpness
from worker.slam import SlamSystem

BLURRED = 8  # the frame where the selector's every-4 rule asks for a keyframe


@pytest.fixture(scope="module")
def frames():
    return list(make_sequence(10_001, num_frames=14, width=160, height=120, revisit=False, use_gt_poses=True))


def _blur(image: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(image, (0, 0), 1.5)


def test_sharpness_drops_with_blur(frames) -> None:
    sharp = [sharpness(f.image) for f in frames]
    blurred = [sharpness(_blur(f.image)) for f in frames]
    assert all(b < 0.35 * s for s, b in zip(sharp, blurred, strict=True)), (sharp, blurred)
    # neighbouring sharp frames score alike (so the recent median is a fair reference)
    assert max(sharp) < 4 * min(sharp)


def test_a_blurred_frame_waits_for_a_sharper_neighbour(frames) -> None:
    selector = MotionKeyframeSelector(every=4, translation=10.0, rotation_deg=90.0, blur_ratio=0.5, blur_delay=2)
    chosen = []
    for f in frames:
        selector.observe(_blur(f.image) if f.index == BLURRED else f.image)
        if selector.is_keyframe(f.pose):
            chosen.append(f.index)
    assert chosen == [0, 4, 9, 13]  # 8 is blurred: 9 instead, and the rhythm follows


def test_the_wait_is_bounded_when_every_frame_is_blurred(frames) -> None:
    selector = MotionKeyframeSelector(every=4, translation=10.0, rotation_deg=90.0, blur_ratio=0.5, blur_delay=2)
    chosen = []
    for f in frames:
        selector.observe(_blur(f.image) if f.index >= BLURRED else f.image)
        if selector.is_keyframe(f.pose):
            chosen.append(f.index)
    assert chosen[:3] == [0, 4, 10]  # two frames late at most, then a blurred keyframe rather than none
    restored = MotionKeyframeSelector(every=4, translation=10.0, rotation_deg=90.0, blur_ratio=0.5)
    restored.load_state_dict(selector.state_dict())
    assert list(restored.recent_sharpness) == list(selector.recent_sharpness)


def test_the_engine_keeps_blurred_frames_out_of_its_keyframes(frames) -> None:
    config = SlamConfig.preset("test", frontend={"keyframe_every": 4, "keyframe_translation": 10.0,
                                                 "keyframe_rotation_deg": 90.0},
                               mapping={"enabled": False}, loop={"enabled": False}, input={"pose_mode": "fixed"})
    system = SlamSystem(config, frames[0].intrinsics)
    keyframes = []
    for f in frames:
        f = replace(f, image=_blur(f.image) if f.index == BLURRED else f.image, depth=None)
        if system.push(f).is_keyframe:
            keyframes.append(f.index)
    system.close()
    assert BLURRED not in keyframes and BLURRED + 1 in keyframes, keyframes
