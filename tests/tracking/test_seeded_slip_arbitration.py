"""pose_mode "seeded" with depth: when the device and the RGB-D odometry disagree, the images decide. The odometry
settling in a wrong place (a slip, as on TUM fr3/cabinet's sparse keyframes) is re-tracked from the device's motion
(`odometry_slip`), not reported as a device jump that would re-anchor the device's world onto the slip; a real
device jump still is one (tests/tracking/test_seeded_tracking.py)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from worker.data import open_source
from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.tracking.base import TrackingResult
from worker.tracking.dense_alignment import AlignmentResult, fit_at, fits_clearly_better
from worker.tracking.rgbd_config import RgbdOdometryConfig
from worker.tracking.rgbd_odometry import RgbdOdometry
from worker.tracking.seeded import SeededTracking
from worker.tracking.seeded_config import DevicePoseConfig

DATA = Path(__file__).parents[1] / "data" / "icl_mini"
SIZE = (160, 120)
SLIP_AT = 8


def _offset(translation: float, rotation_deg: float) -> np.ndarray:
    angle = np.radians(rotation_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    T[:3, 3] = [translation, 0.0, 0.0]
    return T


SLIP = _offset(0.10, 5.0)  # where the slipped alignment settles, in the frame's camera


class SlippingOdometry(RgbdOdometry):
    """Real RGB-D odometry whose first alignment of frame SLIP_AT settles off the true pose (a wrong local minimum
    that passes its checks); the fit it reports is the honest fit of that pose. Tracked again (from the device's
    motion) the frame aligns as usual."""

    def __init__(self, config: RgbdOdometryConfig) -> None:
        super().__init__(config)
        self._slip = False
        self._slipped = False

    def track(self, frame: Frame, intrinsics: Intrinsics | None, motion_guess: np.ndarray | None = None
              ) -> TrackingResult:
        self._slip = frame.index == SLIP_AT and not self._slipped
        self._slipped |= self._slip
        return super().track(frame, intrinsics, motion_guess)

    def _align_to(self, ref, current, guess, K, relocalizing=False):
        pose, reason = super()._align_to(ref, current, guess, K, relocalizing)
        if self._slip and pose is not None:
            pose = pose @ SLIP
            levels = ref.pyramid(K, self.config.pyramid_levels, self.settings.backend)
            self.last_alignment = fit_at(levels, current.pyramid, np.linalg.inv(pose) @ ref.pose, self.settings)
        return pose, reason


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(str(DATA), max_frames=16, resize=SIZE, use_gt_depth=True, use_gt_poses=True))


def _run(frames: list[Frame], arbitrate: bool) -> tuple[SeededTracking, list[TrackingResult]]:
    tracking = SeededTracking(SlippingOdometry(RgbdOdometryConfig()), DevicePoseConfig(arbitrate_jumps=arbitrate))
    intrinsics = frames[0].intrinsics
    return tracking, [tracking.track(replace(f, pose=f.gt_pose.copy()), intrinsics) for f in frames]


def _position_errors(results: list[TrackingResult], frames: list[Frame]) -> np.ndarray:
    return np.array([np.linalg.norm(r.pose[:3, 3] - f.gt_pose[:3, 3]) for r, f in zip(results, frames)])


def test_an_odometry_slip_is_re_tracked_from_the_device_not_called_a_device_jump(frames) -> None:
    tracking, results = _run(frames, arbitrate=True)
    events = [(i, e.TYPE) for i, r in enumerate(results) for e in r.events]
    assert (SLIP_AT, "odometry_slip") in events
    assert not any(kind == "device_pose_jump" for _, kind in events)
    slip = next(e for e in results[SLIP_AT].events if e.TYPE == "odometry_slip")
    assert slip.photometric_rms[1] < slip.photometric_rms[0]  # the images chose the device's side
    errors = _position_errors(results, frames)
    assert errors[SLIP_AT] < 0.015 and errors.max() < 0.02  # where the camera was (the odometry drifts ~1 cm)
    assert np.allclose(tracking.correction, np.eye(4))  # the device's world stays where it was
    assert tracking.slips == 1 and tracking.jumps == 0
    assert all(r.tracked and np.all(np.isfinite(r.pose)) for r in results)


def test_without_arbitration_the_slip_and_its_return_become_device_jumps(frames) -> None:
    tracking, results = _run(frames, arbitrate=False)
    jumps = [i for i, r in enumerate(results) for e in r.events if e.TYPE == "device_pose_jump"]
    # the slip and the odometry's return from it (the next frame aligns to the reference keyframe again) are
    # both taken for device jumps: the device's world re-anchored twice, two keyframe priors dropped
    assert jumps == [SLIP_AT, SLIP_AT + 1]
    assert _position_errors(results, frames)[SLIP_AT] > 0.08 and tracking.jumps == 2


def test_a_fit_is_clearly_better_only_with_a_margin_and_no_lost_overlap() -> None:
    def fit(photometric: float, geometric: float, overlap: float = 0.9) -> AlignmentResult:
        return AlignmentResult(np.eye(4), overlap, photometric, geometric, True, 1000)

    incumbent = fit(0.02, 0.004)
    assert fits_clearly_better(fit(0.015, 0.004), incumbent)  # intensities fit better, depth as well
    assert fits_clearly_better(fit(0.02, 0.003), incumbent)  # depth fits better
    assert not fits_clearly_better(fit(0.019, 0.0039), incumbent)  # within the margin: no decision
    assert not fits_clearly_better(fit(0.01, 0.006), incumbent)  # better intensities, clearly worse depth
    assert not fits_clearly_better(fit(0.01, 0.003, overlap=0.7), incumbent)  # it sees less of the reference
