"""pose_mode "seeded": device poses seed RGB-D odometry and enter the pose graph as keyframe priors; a device jump
(ARKit relocalising) is caught, reported and kept out of the trajectory and the priors; a snapshot continues."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.data.frame import Frame
from worker.eval import absolute_trajectory_error
from worker.events import Initialized
from worker.pipeline.drift import PoseDrift
from worker.slam import SlamSystem
from worker.tracking.base import TrackingResult
from worker.tracking.seeded import DRIFT_PRIOR_LOG_SCALE_SIGMA, SeededTracking
from worker.tracking.seeded_config import DevicePoseConfig

DATA = Path(__file__).parents[1] / "data" / "icl_mini"
SIZE = (160, 120)
JUMP_AT = 14  # the device relocalises here: 15 cm and 4 degrees


def _config(**input_overrides) -> SlamConfig:
    # keyframes on the preset's every-6 schedule alone (parallax off): the prior checks below are sized for the
    # drift those keyframes carry after the jump
    return SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False}, frontend={"keyframe_parallax": 1.0},
                             input={"pose_mode": "seeded", **input_overrides})


def _run(frames, device_poses: list[np.ndarray], config: SlamConfig):
    system = SlamSystem(config)
    results = []
    for frame, device in zip(frames, device_poses):
        results.append(system.push(replace(frame, pose=device.copy())))  # the shared frames keep their true poses
    system.finish()
    return system, results


def _ate(poses, frames) -> float:
    return absolute_trajectory_error(np.stack(poses), np.stack([f.gt_pose for f in frames]), "sim3").rmse


@pytest.fixture(scope="module")
def frames():
    return list(open_source(str(DATA), max_frames=30, resize=SIZE, use_gt_depth=True, use_gt_poses=True))


@pytest.fixture(scope="module")
def drifted(frames) -> list[np.ndarray]:
    """Device poses that drift (0.3 deg and 4 mm per frame, compounded) and jump at frame JUMP_AT."""
    drift = PoseDrift(0.3, 0.004, 0.1, 0.001, seed=3, jump_frame=JUMP_AT, jump_translation=0.15,
                      jump_rotation_deg=4.0)
    return list(drift.apply_to_trajectory(np.stack([f.gt_pose for f in frames])))


@pytest.fixture(scope="module")
def seeded_run(frames, drifted):
    return _run(frames, drifted, _config())


def test_a_device_jump_is_caught_reported_and_kept_out_of_the_trajectory(frames, drifted, seeded_run) -> None:
    system, results = seeded_run
    assert isinstance(system.pose_source, SeededTracking) and system.mode == "posed"
    jumps = [(r.index, e) for r in results for e in r.events if e.TYPE == "device_pose_jump"]
    assert [i for i, _ in jumps] == [JUMP_AT]
    assert jumps[0][1].translation > 0.1 and jumps[0][1].rotation_deg > 3.0
    device_steps = [np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(drifted, drifted[1:])]
    tracked_steps = [np.linalg.norm(b.pose[:3, 3] - a.pose[:3, 3]) for a, b in zip(results, results[1:])]
    true_steps = [np.linalg.norm(b.gt_pose[:3, 3] - a.gt_pose[:3, 3]) for a, b in zip(frames, frames[1:])]
    assert abs(device_steps[JUMP_AT - 1] - true_steps[JUMP_AT - 1]) > 0.1  # the device's poses jump there ...
    assert max(abs(t - g) for t, g in zip(tracked_steps, true_steps)) < 0.02  # ... the session's do not
    assert all(np.all(np.isfinite(r.pose)) for r in results)


def test_keyframe_priors_reach_the_pose_graph_except_after_the_jump(drifted, seeded_run) -> None:
    system, results = seeded_run
    source = system.pose_source
    keyframes = [r.index for r in results if r.is_keyframe]
    priors = system.pose_graph.priors
    assert source.priors_dropped == 1 and len(priors) == len(keyframes) - 1
    dropped = next(k for k in keyframes if k >= JUMP_AT)  # the first keyframe after the jump has no prior
    assert dropped not in {p.key for p in priors}
    assert all(p.sigmas.translation >= 0.10 and p.sigmas.rotation >= np.radians(2.0) for p in priors)
    # priors after the jump are re-anchored: the jump (15 cm, 4 deg) does not reach them
    poses = dict((i, p) for i, _, p in system.trajectory("keyframes"))
    after = [p for p in priors if p.key > JUMP_AT]
    assert after
    for prior in after:
        off = np.linalg.norm(prior.pose[:3, 3] - poses[prior.key][:3, 3])
        raw_off = np.linalg.norm(drifted[prior.key][:3, 3] - poses[prior.key][:3, 3])
        assert off < raw_off - 0.08, (off, raw_off)


def test_seeded_tracking_beats_the_drifted_device_poses(frames, drifted, seeded_run) -> None:
    system, results = seeded_run
    seeded = _ate([r.pose for r in results], frames)
    device = _ate(drifted, frames)
    assert seeded < 0.5 * device, (seeded, device)
    prior_system, prior_results = _run(frames, drifted, _config().model_copy(
        update={"input": _config().input.model_copy(update={"pose_mode": "prior"})}))
    assert seeded < 0.5 * _ate([r.pose for r in prior_results], frames)  # device poses taken as they are


def test_a_seeded_session_continues_from_a_snapshot(frames, drifted) -> None:
    system = SlamSystem(_config())
    for frame, device in list(zip(frames, drifted))[:10]:
        frame.pose = device.copy()
        system.push(frame)
    restored = SlamSystem.restore(system.snapshot())
    assert isinstance(restored.pose_source, SeededTracking)
    for frame, device in list(zip(frames, drifted))[10:16]:
        frame.pose = device.copy()
        a, b = system.push(frame), restored.push(frame)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-3)  # references are snapshot as uint8 / float16
    system.close()
    restored.close()


def test_without_depth_visual_odometry_is_seeded_in_the_device_world_and_scale(frames) -> None:
    system = SlamSystem(_config(use_depth=False))
    results = [system.push(frame) for frame in frames]  # true poses as the device's
    system.finish()
    source = system.pose_source
    assert isinstance(source, SeededTracking) and source.monocular and source.alignment is not None
    poses = np.stack([p for _, _, p in system.trajectory("all")])
    truth = np.stack([f.gt_pose for f in frames])
    np.testing.assert_allclose(poses[0], truth[0], atol=1e-6)  # the device's world, not the odometry's
    path = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()
    true_path = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum()
    assert abs(path / true_path - 1.0) < 0.1  # metric: the scale comes from the device's baseline
    assert absolute_trajectory_error(poses, truth, "se3").rmse < 0.05
    assert all(np.all(np.isfinite(r.pose)) for r in results)


def test_without_depth_the_pose_graph_brings_the_keyframes_to_a_device_whose_scale_drifts(frames) -> None:
    """drift_correction pose_graph through the engine, real ICL frames: device poses whose steps grow 1.5 % a frame
    (the images keep their scale, so the odometry and the device part), stated at 1 cm. The graph is solved every
    two priors: the session reports `drift_corrected` with the revision it made, and the corrected keyframes lie
    nearer the device's poses than the odometry's."""
    device = [frames[0].gt_pose.copy()]
    for n in range(1, len(frames)):
        step = np.linalg.inv(frames[n - 1].gt_pose) @ frames[n].gt_pose
        step[:3, 3] *= 1.015 ** n
        device.append(device[-1] @ step)
    config = _config(use_depth=False, device_poses={"drift_correction": "pose_graph", "graph_solve_keyframes": 2,
                                                    "prior_translation": 0.01, "prior_inflation": 0.0})
    system, results = _run(frames, device, config)
    corrected = [e for r in results for e in r.events if e.TYPE == "drift_corrected"] + [
        e for e in system.finish_events if e.TYPE == "drift_corrected"]
    assert corrected and all(e.revision is not None for e in corrected)
    assert system.counters["drift_corrections"] == len(corrected)
    trajectory = system.tracking_stage.trajectory
    keyframes = sorted(trajectory.keyframe_poses)
    assert len(keyframes) >= 4

    def distance(poses: dict[int, np.ndarray]) -> float:
        return float(np.mean([np.linalg.norm(poses[k][:3, 3] - device[k][:3, 3]) for k in keyframes]))

    # the graph weighs the odometry's edges too (and priors far off through a robust kernel): nearer, not on them
    assert distance(trajectory.keyframe_poses) < 0.8 * distance(trajectory.tracked_keyframe_poses)
    assert all(np.all(np.isfinite(p)) for _, _, p in system.trajectory("all"))


class _ScaleDriftingOdometry:
    """Monocular odometry reduced to its scale problem: the true motion at a scale that shrinks 0.5 % per frame
    (constructed geometry, no images); its map is made at frame 2, the frames before re-estimated."""

    name = "scale_drifting"
    status = "tracking"

    def __init__(self, truth: list[np.ndarray]) -> None:
        self.truth, self.position, self.frame = truth, np.zeros(3), 0

    def track(self, frame, intrinsics, motion_guess=None) -> TrackingResult:
        n = frame.index
        pose = self.truth[n].copy()
        if n > 0:
            self.position = self.position + 0.5 * 0.995 ** n * (self.truth[n][:3, 3] - self.truth[n - 1][:3, 3])
        pose[:3, 3] = self.position
        events = [Initialized(frames=[[0, np.eye(4).tolist()], [1, pose.tolist()]])] if n == 2 else []
        return TrackingResult(pose, tracked=True, events=events, quality=1.0)

    def keyframe_added(self, frame, pose) -> None:
        pass


def _curve(steps: int = 80) -> list[np.ndarray]:
    """A 4 m walk round a curve, turning 1 degree per frame."""
    truth = []
    for n in range(steps):
        pose = np.eye(4)
        yaw = np.radians(n)
        pose[:3, :3] = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        pose[:3, 3] = [2.0 * np.sin(yaw), 0.0, 2.0 * (1 - np.cos(yaw))]
        truth.append(pose)
    truth[0][:3, :3] = np.eye(3)
    return truth


def _track_seeded(odometry, truth: list[np.ndarray], config: DevicePoseConfig, publish_prior=None,
                  after_frame=None) -> tuple[SeededTracking, list[TrackingResult]]:
    """A constructed monocular odometry seeded with the true poses, a keyframe every third frame;
    `after_frame(n, tracking)` looks at the tracker after each frame."""
    tracking = SeededTracking(odometry, config, monocular=True, publish_prior=publish_prior)
    results = []
    for n, pose in enumerate(truth):
        frame = Frame(n, n / 30.0, np.zeros((4, 4, 3), np.uint8), pose=pose.copy())
        results.append(tracking.track(frame, None))
        if n % 3 == 0:
            tracking.keyframe_added(frame, results[-1].pose)
        if after_frame is not None:
            after_frame(n, tracking)
    return tracking, results


def _track_drifting(truth: list[np.ndarray], config: DevicePoseConfig, publish_prior=None
                    ) -> tuple[SeededTracking, list[TrackingResult]]:
    """The scale-drifting odometry seeded with the true poses, a keyframe every third frame."""
    return _track_seeded(_ScaleDriftingOdometry(truth), truth, config, publish_prior)


@pytest.mark.parametrize("scale_keyframes", [8, 0])
def test_without_depth_the_scale_follows_the_device_as_the_odometry_drifts(scale_keyframes: int) -> None:
    truth = _curve()
    _, results = _track_drifting(truth, DevicePoseConfig(scale_keyframes=scale_keyframes, drift_correction="reanchor"))
    outputs = [r.pose for r in results]
    step = lambda poses: np.linalg.norm(np.diff(np.stack(poses)[-20:, :3, 3], axis=0), axis=1).sum()  # noqa: E731
    ratio = step(outputs) / step(truth)  # the last 20 frames: the odometry's scale is 0.7 of the first frames'
    if scale_keyframes:
        assert abs(ratio - 1.0) < 0.12  # measured over the last 8 keyframes (24 frames): it lags a little
    else:
        assert ratio < 0.75  # the initial scale alone: the odometry's drift goes through
    assert all(np.all(np.isfinite(p)) for p in outputs)
    steps_out = np.linalg.norm(np.diff(np.stack(outputs)[:, :3, 3], axis=0), axis=1)
    assert steps_out.max() < 3 * np.median(steps_out)  # re-anchoring at keyframes never makes a pose jump


@pytest.mark.parametrize("drift_correction", ["settle", "pose_graph"])
def test_the_scale_settles_over_the_first_window_and_the_odometry_keeps_it(drift_correction: str) -> None:
    """drift_correction settle and pose_graph: the scale is re-measured over the first full window of
    keyframes (the initialisation's is a two-view guess), then the output keeps it (the map stays at one scale)
    while the device still measures the drifting scale (seeds, jump checks), so the drift is no device jump. With
    pose_graph the keyframe priors leave the node's scale to the odometry's edges."""
    truth = _curve()
    priors = []
    tracking, results = _track_drifting(truth, DevicePoseConfig(drift_correction=drift_correction), priors.append)
    assert tracking.scale_settled
    settled_at = 3 * 8  # the 9th keyframe mark
    outputs = [r.pose for r in results]
    step = lambda poses: np.linalg.norm(np.diff(np.stack(poses)[-20:, :3, 3], axis=0), axis=1).sum()  # noqa: E731
    drift = 0.995 ** (70 - settled_at)  # the odometry's scale in the last frames over its scale when settled
    assert step(outputs) / step(truth) == pytest.approx(drift, rel=0.08)  # the drift goes through
    assert tracking.measured_scale / tracking.scale == pytest.approx(1 / drift, rel=0.08)
    assert not any(e.TYPE == "device_pose_jump" for r in results for e in r.events)
    assert len(priors) == len(range(0, 80, 3))  # every keyframe
    free_scale = [p.sigmas.log_scale == DRIFT_PRIOR_LOG_SCALE_SIGMA for p in priors]
    assert all(free_scale) if drift_correction == "pose_graph" else not any(free_scale)
    np.testing.assert_allclose(priors[-1].pose, truth[78], atol=1e-9)  # the device's pose, in the device world
    assert all(np.all(np.isfinite(p)) for p in outputs)


def test_a_settled_scale_is_measured_again_in_steps_where_the_odometry_drifts_past_the_tolerance() -> None:
    """drift_correction settle with `settle_tolerance` 0.1: the odometry shrinks 0.5 % a frame, so the kept scale is
    10 % off within about 20 frames; the world is then re-anchored once at the measured scale and kept at it again.
    The output follows the device's scale to within the tolerance (plus the window's lag), in a few steps, not at
    every keyframe, and no pose jumps."""
    truth = _curve()
    scales = []
    config = DevicePoseConfig(drift_correction="settle", settle_tolerance=0.1)
    _, results = _track_seeded(_ScaleDriftingOdometry(truth), truth, config,
                               after_frame=lambda n, tracking: scales.append(tracking.scale))
    settled_at = 3 * 9  # the 9th keyframe mark (the first keyframe comes before the odometry's map)
    changes = [n for n in range(settled_at + 1, len(scales)) if scales[n] != scales[n - 1]]
    assert 1 <= len(changes) <= 3  # steps of ~10 %: 0.995 ** 55 is 24 % of drift (0: none)
    outputs = [r.pose for r in results]
    step = lambda poses: np.linalg.norm(np.diff(np.stack(poses)[-20:, :3, 3], axis=0), axis=1).sum()  # noqa: E731
    assert abs(step(outputs) / step(truth) - 1.0) < 0.15  # kept at the settled scale: 24 % short
    steps_out = np.linalg.norm(np.diff(np.stack(outputs)[:, :3, 3], axis=0), axis=1)
    assert steps_out.max() < 3 * np.median(steps_out)
    assert all(np.all(np.isfinite(p)) for p in outputs)


def test_a_device_jump_unsettles_the_scale_until_a_full_window_measures_it_again() -> None:
    """drift_correction settle: a device jump (0.5 m at frame 45, after the scale settled) restarts the scale's
    window: distances across it measure nothing, and the kept scale may be what made the odometry disagree."""
    truth = _curve()
    device = [p.copy() for p in truth]
    for pose in device[45:]:
        pose[:3, 3] += [0.5, 0.0, 0.0]
    tracking = SeededTracking(_ScaleDriftingOdometry(truth), DevicePoseConfig(drift_correction="settle"),
                              monocular=True, publish_prior=lambda prior: None)
    settled, jumps = [], []
    for n, pose in enumerate(device):
        frame = Frame(n, n / 30.0, np.zeros((4, 4, 3), np.uint8), pose=pose.copy())
        result = tracking.track(frame, None)
        jumps += [n for e in result.events if e.TYPE == "device_pose_jump"]
        if n % 3 == 0:
            tracking.keyframe_added(frame, result.pose)
        settled.append(tracking.scale_settled)
    assert jumps == [45]
    assert settled[44] and not settled[45]  # settled before the jump, measured again after it
    assert not any(settled[45:45 + 3 * 8]) and settled[-1]  # until a full window (9 keyframes) measured it


def _scaled_steps(poses: list[np.ndarray], factor: float) -> list[np.ndarray]:
    """Poses whose every step moves `factor` times as far (a device whose scale is off)."""
    out = [poses[0].copy()]
    for a, b in zip(poses, poses[1:]):
        step = np.linalg.inv(a) @ b
        step[:3, 3] *= factor
        out.append(out[-1] @ step)
    return out


def _jump_frames(frames, device_poses, jump_relative: float) -> list[int]:
    config = _config(device_poses={"jump_relative": jump_relative})
    _, results = _run(frames, device_poses, config)
    return [r.index for r in results for e in r.events if e.TYPE == "device_pose_jump"]


def test_jump_thresholds_grow_with_the_motion_of_sparse_frames() -> None:
    """Every other frame (steps up to 21 cm) with a device 35 % off in scale: its disagreement with the odometry
    grows with each step (up to 7 cm) and is not a jump; a 15 cm relocalisation on the same frames is one."""
    sparse = list(open_source(str(DATA), stride=2, resize=SIZE, use_gt_depth=True, use_gt_poses=True))
    truth = [f.gt_pose for f in sparse]
    device = _scaled_steps(truth, 1.35)
    assert _jump_frames(sparse, device, jump_relative=0.0)  # absolute thresholds alone call these jumps
    assert _jump_frames(sparse, device, jump_relative=0.25) == []
    jumped = PoseDrift(0.0, 0.0, 0.0, 0.0, seed=3, jump_frame=8, jump_translation=0.15,
                       jump_rotation_deg=4.0).apply_to_trajectory(np.stack(device))
    assert _jump_frames(sparse, list(jumped), jump_relative=0.25) == [sparse[8].index]


class _TurnHoldingOdometry:
    """Monocular odometry through a curve that, over frames `held`, follows the turn by rotation alone: the right
    orientation, its position held (as visual odometry's turn models report, `translation_measured` False)."""

    name = "turn_holding"
    status = "tracking"

    def __init__(self, truth: list[np.ndarray], held: range) -> None:
        self.truth, self.held, self.position = truth, held, np.zeros(3)

    def track(self, frame, intrinsics, motion_guess=None) -> TrackingResult:
        n = frame.index
        pose = self.truth[n].copy()
        measured = n not in self.held
        if measured:
            self.position = pose[:3, 3].copy()
        pose[:3, 3] = self.position
        events = [Initialized(frames=[[0, np.eye(4).tolist()], [1, self.truth[1].tolist()]])] \
            if n == 2 else []
        return TrackingResult(pose, tracked=True, events=events, quality=1.0 if measured else 0.3,
                              translation_measured=measured)

    def keyframe_added(self, frame, pose) -> None:
        pass


def test_a_turn_followed_by_rotation_alone_takes_the_device_position_and_is_no_jump() -> None:
    truth = []
    for n in range(40):  # 1 m a frame round a curve, turning 3 degrees a frame
        pose = np.eye(4)
        yaw = np.radians(3.0 * n)
        pose[:3, :3] = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        pose[:3, 3] = [n * np.sin(yaw / 2), 0.0, n * np.cos(yaw / 2)]
        truth.append(pose)
    truth[0] = np.eye(4)
    truth[1][:3, :3] = np.eye(3)
    held = range(20, 26)
    tracking = SeededTracking(_TurnHoldingOdometry(truth, held), DevicePoseConfig(scale_keyframes=0), monocular=True)
    results = [tracking.track(Frame(n, n / 10.0, np.zeros((4, 4, 3), np.uint8), pose=pose.copy()), None)
               for n, pose in enumerate(truth)]
    assert not [e for r in results for e in r.events if e.TYPE == "device_pose_jump"]
    positions = np.stack([r.pose[:3, 3] for r in results])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    true_steps = np.linalg.norm(np.diff(np.stack([p[:3, 3] for p in truth]), axis=0), axis=1)
    np.testing.assert_allclose(steps[15:], true_steps[15:], rtol=0.02)  # the held frames move with the device
    for n in held:  # and keep the odometry's orientation
        np.testing.assert_allclose(results[n].pose[:3, :3], truth[n][:3, :3], atol=1e-6)



class _RestartingOdometry:
    """Monocular odometry (constructed geometry, no images) that loses its map at LOST_AT and makes a new one at
    MAP_AT, continuing its old world at a tenth of the old scale from where it was lost: the new map's first
    frame keeps the lost pose as a placeholder (as visual odometry's re-initialisation reports it), the others are
    re-estimated at the new scale."""

    name = "restarting"
    LOST_AT, REFERENCE, MAP_AT, NEW_SCALE = 30, 33, 38, 0.1

    def __init__(self, truth: list[np.ndarray]) -> None:
        self.truth, self.status = truth, "tracking"
        self.lost_pose: np.ndarray | None = None

    def _at(self, n: int) -> np.ndarray:
        """The odometry's pose of frame n: the old world at scale 0.5 before the loss, the new map after it."""
        pose = self.truth[n].copy()
        if n < self.LOST_AT:
            pose[:3, 3] = 0.5 * self.truth[n][:3, 3]
        else:
            moved = self.truth[n][:3, 3] - self.truth[self.REFERENCE][:3, 3]
            pose[:3, 3] = self.lost_pose[:3, 3] + self.NEW_SCALE * moved
        return pose

    def track(self, frame, intrinsics, motion_guess=None) -> TrackingResult:
        n = frame.index
        if n == self.LOST_AT:
            self.lost_pose = self._at(n - 1)
        events = [Initialized(frames=[[0, np.eye(4).tolist()], [1, self._at(1).tolist()]])] \
            if n == 2 else []
        if self.LOST_AT <= n < self.MAP_AT:
            self.status = "initializing"
            return TrackingResult(self.lost_pose.copy(), tracked=False)
        if n == self.MAP_AT:
            self.status = "tracking"
            placeholder = self._at(self.REFERENCE)
            placeholder[:3, :3] = self.truth[self.REFERENCE - 1][:3, :3]
            frames = [[self.REFERENCE - 1, placeholder.tolist()]]
            frames += [[i, self._at(i).tolist()] for i in range(self.REFERENCE, n)]
            events = [Initialized(frames=frames)]
        return TrackingResult(self._at(n), tracked=True, events=events, quality=1.0)

    def keyframe_added(self, frame, pose) -> None:
        pass


@pytest.mark.parametrize("drift_correction", ["settle", "reanchor"])
def test_a_new_map_after_a_loss_takes_the_device_scale_again(drift_correction: str) -> None:
    """Seeded visual odometry that lost its map makes a new one at a new scale, in its old world, its first
    frame a placeholder: the new map is scaled from the device's steps over the frames it re-estimated (not over
    the placeholder's), so the output keeps moving with the device, no device jump is called, and the scale's
    window is measured again."""
    truth = _curve(80)
    odometry = _RestartingOdometry(truth)
    window_at_new_map = []

    def look(n: int, tracking: SeededTracking) -> None:
        if n == odometry.MAP_AT:
            window_at_new_map.append((tracking.scale_settled, len(tracking.scale_marks)))

    _, results = _track_seeded(odometry, truth, DevicePoseConfig(drift_correction=drift_correction),
                               lambda prior: None, look)
    assert window_at_new_map == [(False, 0)]
    assert not [e for r in results for e in r.events if e.TYPE == "device_pose_jump"]
    steps = np.linalg.norm(np.diff(np.stack([r.pose[:3, 3] for r in results]), axis=0), axis=1)
    true_steps = np.linalg.norm(np.diff(np.stack([p[:3, 3] for p in truth]), axis=0), axis=1)
    np.testing.assert_allclose(steps[odometry.MAP_AT:], true_steps[odometry.MAP_AT:], rtol=0.02)
    assert all(np.all(np.isfinite(r.pose)) for r in results)
