"""RGB-D frames without intrinsics: the focal length is estimated from the images and depth (real ICL frames,
tests/data/icl_mini, true focal 262.5 px at 320x240), from guesses far off on both sides; the odometry then
re-tracks the frames it collected and reports them; the engine maps with the estimated camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.config import SlamConfig
from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem
from worker.tracking.focal_calibration import estimate_focal
from worker.tracking.rgbd_config import RgbdOdometryConfig
from worker.tracking.rgbd_odometry import RgbdOdometry, grey_of

DATA = Path(__file__).parents[1] / "data" / "icl_mini"
TRUE_FOCAL = 262.5


@pytest.fixture(scope="module")
def frames():
    out = list(open_source(str(DATA), use_gt_depth=True, max_frames=24))
    for f in out:
        f.intrinsics = None  # a camera nobody told us about
    return out


@pytest.mark.parametrize("guess", [190.0, 380.0])
def test_the_focal_length_is_found_from_a_wrong_guess(frames, guess) -> None:
    pairs = [((grey_of(frames[0].image), frames[0].depth), (grey_of(f.image), f.depth)) for f in (frames[4],
                                                                                                  frames[2])]
    estimate = estimate_focal(pairs, guess, (160.0, 120.0))
    assert estimate.trusted and abs(estimate.focal / TRUE_FOCAL - 1) < 0.03


def test_a_textureless_pair_keeps_the_guess(frames) -> None:
    grey = np.full((240, 320), 0.5, np.float32)
    flat = np.full((240, 320), 2.0, np.float32)
    estimate = estimate_focal([((grey, flat), (grey, flat))], 300.0, (160.0, 120.0))
    assert not estimate.trusted and estimate.focal == 300.0


def test_odometry_calibrates_then_reports_the_frames_again(frames) -> None:
    odometry = RgbdOdometry(RgbdOdometryConfig(focal_guess=1.2))  # 384 px: 46 % too long
    results = [odometry.track(f, None) for f in frames]
    events = [(k, e) for k, r in enumerate(results) for e in r.events]
    assert [e.TYPE for _, e in events] == ["initialized"]
    at, event = events[0]
    assert 4 <= at < 24 and not odometry.calibrating
    assert abs(event.intrinsics["fx"] / TRUE_FOCAL - 1) < 0.03 and event.focal_trusted
    assert [i for i, _ in event.frames] == [f.index for f in frames[:at]]
    assert all(not r.keyframe_hint for r in results[1:at])  # no keyframes on the guessed camera
    poses = [np.asarray(p) for _, p in event.frames] + [r.pose for r in results[at:]]
    gt = np.stack([f.gt_pose for f in frames])
    assert absolute_trajectory_error(np.stack(poses), gt, "se3").rmse < 0.03


def test_calibration_survives_a_snapshot(frames) -> None:
    odometry = RgbdOdometry()
    for f in frames[:3]:
        odometry.track(f, None)
    assert odometry.calibrating
    restored = RgbdOdometry()
    restored.load_state_dict(unpack(pack(odometry.state_dict())))
    events = [e for f in frames[3:] for e in restored.track(f, None).events]
    assert [e.TYPE for e in events] == ["initialized"] and len(events[0].frames) >= 3


def test_the_engine_maps_with_the_estimated_camera(frames) -> None:
    system = SlamSystem(SlamConfig.preset("rgbd", threaded=False, mapping={"refine_iterations": 1,
                                                                          "final_refine_passes": 0}))
    for f in frames:
        system.push(f)
    system.finish()
    camera = system.estimated_intrinsics()
    assert system.mode == "rgbd_odometry" and abs(camera.fx / TRUE_FOCAL - 1) < 0.03
    index, _, pose = system.trajectory()[12]
    rgb, _ = system.render_view(pose, camera.matrix(), camera.width, camera.height)
    assert float(np.abs(rgb.astype(np.float32) - frames[12].image).mean()) < 20
    system.close()
