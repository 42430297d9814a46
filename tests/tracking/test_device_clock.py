"""The device pose clock (worker.tracking.device_clock): its offset measured on real frames, the re-timing, snapshots.

Real frames: TUM fr1/xyz (tests/data/tum_fr1_xyz_mini, motion capture whose clock runs about +8 ms ahead of the
Kinect's: bench/results/device_clock/) and ICL living room (tests/data/icl_mini, 10 Hz, poses made from the frames
themselves: no offset of their own).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from worker.config import SlamConfig
from worker.data import open_source
from worker.geometry.transforms import so3_exp
from worker.tracking.device_clock import DeviceClock
from worker.tracking.factory import build_pose_source
from worker.tracking.pose_interpolation import interpolate_poses
from worker.tracking.seeded_config import DeviceClockConfig
from worker.tracking.sources import DevicePoses

DATA = Path(__file__).resolve().parents[1] / "data"
TUM_NATIVE_MS = 8.0  # the motion capture's own offset on these frames (6-10 ms on every 48-frame stretch)


@pytest.fixture(scope="module")
def tum():
    source = open_source(str(DATA / "tum_fr1_xyz_mini"), use_gt_poses=True)
    return list(source), source.intrinsics


@pytest.fixture(scope="module")
def icl():
    source = open_source(str(DATA / "icl_mini"), use_gt_poses=True)
    return list(source), source.intrinsics


def shifted(frames, offset_s: float, depth: bool = True):
    """The frames with device poses `offset_s` ahead of the camera: their poses read at timestamp + offset_s."""
    times = np.array([f.timestamp for f in frames])
    poses = interpolate_poses(times, np.stack([f.pose for f in frames]), times + offset_s, 0.15)
    return [replace(f, pose=p, depth=f.depth if depth else None) for f, p in zip(frames, poses)]


def measured(frames, intrinsics, final: bool = True, **config) -> DeviceClock:
    config = {"window_frames": len(frames), "max_frames": len(frames), **config}
    clock = DeviceClock(DeviceClockConfig(**config))
    for frame in frames:
        clock.pose_at(frame, intrinsics)
    assert clock.measuring != final
    return clock


@pytest.mark.parametrize("depth", [True, False], ids=["depth", "epipolar"])
def test_a_40_ms_offset_injected_into_real_kinect_frames_is_found(tum, depth):
    frames, intrinsics = tum
    native = measured(shifted(frames, 0.0, depth), intrinsics)
    ahead = measured(shifted(frames, 0.040, depth), intrinsics)
    assert native.estimate.offset_s * 1000 == pytest.approx(TUM_NATIVE_MS, abs=4.0)
    assert ahead.estimate.offset_s * 1000 == pytest.approx(40 + TUM_NATIVE_MS, abs=6.0)
    assert ahead.estimate.uncertainty_s < 0.005
    assert ahead.target_offset_s == ahead.estimate.offset_s  # applied, reached by 1 ms a frame
    assert ahead.offset_s == pytest.approx(0.001)


def test_exact_icl_poses_keep_no_offset_and_an_injected_one_is_found(icl):
    frames, intrinsics = icl  # 10 Hz: pairs 100 ms apart
    exact = measured(shifted(frames, 0.0), intrinsics, search_s=0.08)
    assert exact.target_offset_s == 0.0
    assert exact.estimate.offset_s is None or abs(exact.estimate.offset_s) <= 2 * exact.estimate.uncertainty_s
    ahead = measured(shifted(frames, 0.040), intrinsics, search_s=0.08)
    assert ahead.target_offset_s * 1000 == pytest.approx(40.0, abs=5.0)


def test_a_still_stream_is_not_estimated(icl):
    frames, intrinsics = icl
    still = [replace(frames[0], index=i, timestamp=i / 30.0) for i in range(40)]
    clock = measured(still[:-1], intrinsics, offset_s=0.012, window_frames=40, max_frames=40, final=False)
    assert clock.measuring and not clock.pairs.pairs  # nothing kept: a snapshot of a still stream stays small
    clock.pose_at(still[-1], intrinsics)
    assert not clock.measuring
    assert clock.estimate.offset_s is None and "with motion" in clock.estimate.reason
    assert clock.offset_s == pytest.approx(0.012)  # the given offset is kept
    assert clock.summary()["estimate"]["estimated"] is False


def test_measuring_in_the_background_finds_what_inline_measuring_finds(tum):
    """Threaded sessions measure on the clock's own thread: the same pairs, the same estimate; the tracking thread
    applies it once done, and a snapshot taken meanwhile waits for the frames handed over."""
    frames, intrinsics = tum
    device = shifted(frames, 0.040)
    config = DeviceClockConfig(window_frames=len(frames) - 8, max_frames=len(frames) - 8)
    inline, background = DeviceClock(config), DeviceClock(config, background=True)
    for frame in device[:20]:
        inline.pose_at(frame, intrinsics)
        background.pose_at(frame, intrinsics)
    mid = background.state_dict()  # waits for the hand-overs so far
    assert [p.t1 for p in background.pairs.pairs] == [p.t1 for p in inline.pairs.pairs]
    assert mid["pairs"]["pairs"] and background.measuring
    for frame in device[20:]:
        inline.pose_at(frame, intrinsics)
        background.pose_at(frame, intrinsics)
    assert not inline.measuring
    background.finish_measuring()
    assert not background.measuring and background._worker is None
    assert background.estimate == inline.estimate
    assert background.target_offset_s == inline.target_offset_s != 0.0


def test_interpolation_retimes_a_known_trajectory_exactly():
    omega, velocity = np.array([0.3, -0.5, 0.2]), np.array([0.4, 0.1, -0.2])  # rad/s, m/s

    def truth(t: np.ndarray) -> np.ndarray:
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, :3] = so3_exp(torch.from_numpy(t[:, None] * omega)).numpy()
        out[:, :3, 3] = np.array([1.0, 2.0, 0.5]) + t[:, None] * velocity
        return out

    times = np.arange(20) / 30.0
    queries = np.array([0.0, 0.0123, 0.31, 19 / 30.0 - 0.001])
    np.testing.assert_allclose(interpolate_poses(times, truth(times), queries), truth(queries), atol=1e-12)
    # past the newest pose: constant velocity, at most max_extrapolation_s
    ahead = interpolate_poses(times, truth(times), np.array([times[-1] + 0.02, times[-1] + 0.2]), 0.05)
    np.testing.assert_allclose(ahead, truth(np.array([times[-1] + 0.02, times[-1] + 0.05])), atol=1e-12)


def test_a_given_offset_retimes_the_device_poses(tum):
    frames, intrinsics = tum
    clock = DeviceClock(DeviceClockConfig(mode="off", offset_s=0.040))
    device = shifted(frames, 0.040)
    out = [clock.pose_at(f, intrinsics) for f in device]
    # from the second frame the pose read 40 ms back lies between received ones: it is the frame's own pose again
    errors = [np.linalg.norm(p[:3, 3] - f.pose[:3, 3]) for p, f in zip(out[2:], frames[2:])]
    raw = [np.linalg.norm(d.pose[:3, 3] - f.pose[:3, 3]) for d, f in zip(device[2:], frames[2:])]
    assert np.median(errors) < 0.2 * np.median(raw)


def clocked(config: DeviceClockConfig | None = None) -> DevicePoses:
    source = DevicePoses()
    source.device_clock = DeviceClock(config)
    return source


def test_state_dict_round_trip_mid_measurement(tum):
    frames, intrinsics = tum
    device = shifted(frames, 0.040)
    config = DeviceClockConfig(window_frames=len(frames), max_frames=len(frames))
    straight, first = clocked(config), clocked(config)
    for frame in device[:30]:
        straight.track(frame, intrinsics)
        first.track(frame, intrinsics)
    restored = clocked(config)
    restored.load_state_dict(first.state_dict())
    for frame in device[30:]:
        a, b = straight.track(frame, intrinsics), restored.track(frame, intrinsics)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-9)
    assert restored.device_clock.estimate == straight.device_clock.estimate
    assert restored.device_clock.offset_s == straight.device_clock.offset_s != 0.0
    assert restored.device_clock.target_offset_s == straight.device_clock.target_offset_s
    again = clocked(config)
    again.load_state_dict(restored.state_dict())
    assert again.device_clock.summary() == restored.device_clock.summary()


def test_a_snapshot_from_before_the_clock_restores_its_source():
    source = DevicePoses()
    source.last_pose = np.diag([1.0, 1.0, 1.0, 1.0])
    restored = clocked()
    restored.load_state_dict(source.state_dict())
    np.testing.assert_array_equal(restored.last_pose, source.last_pose)
    assert not restored.device_clock.measuring


def test_the_factory_clocks_device_sources_only_when_asked():
    config = SlamConfig.preset("test")
    assert build_pose_source("device", config, False, lambda prior: None).device_clock is not None
    off = config.model_copy(update={"input": config.input.model_copy(
        update={"device_clock": DeviceClockConfig(mode="off")})})
    assert build_pose_source("device", off, False, lambda prior: None).device_clock is None


def test_a_session_snapshot_keeps_the_clock_measuring(tum):
    """Snapshot (msgpack) mid-measurement, restored as on another worker: both sessions measure the same offset."""
    from worker.slam import SlamSystem

    frames, intrinsics = tum
    config = SlamConfig.preset("test")
    clock = config.input.device_clock.model_copy(update={"window_frames": 40})
    config = config.model_copy(update={"threaded": False, "input": config.input.model_copy(
        update={"device_clock": clock})})
    system = SlamSystem(config, intrinsics=intrinsics)
    for frame in frames[:25]:
        system.push(frame)
    restored = SlamSystem.restore(system.snapshot())
    try:
        assert restored.stats()["device_clock"] == system.stats()["device_clock"]
        for frame in frames[25:]:
            system.push(frame)
            restored.push(frame)
        measured = system.stats()["device_clock"]
        assert measured["estimate"]["estimated"] and restored.stats()["device_clock"] == measured
    finally:
        system.close()
        restored.close()
