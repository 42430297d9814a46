"""Submap tracker (paper 4.1) driven by the ground-truth model double on the ICL living-room frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worker.frontend.tracker import SubmapTracker, TrackerConfig, relative_scale
from worker.geometry import relative_transform
from worker.loop.oracle import OracleModel, load_rgbd_folder
from worker.loop.synthetic import ate_rmse


@pytest.fixture(scope="module")
def icl_frames(request):
    from pathlib import Path

    return load_rgbd_folder(Path(request.config.rootpath) / "tests" / "data" / "icl_mini", downscale=2)


def _run(tracker: SubmapTracker, frames, indices):
    return [tracker.track(n, frames[n].image, frames[n].intrinsics) for n in indices]


def test_chained_submaps_recover_the_trajectory_up_to_one_similarity(icl_frames):
    tracker = SubmapTracker(OracleModel(icl_frames, point_noise=0.01), TrackerConfig(submap_length=8))
    tracked = _run(tracker, icl_frames, range(len(icl_frames)))
    est = np.stack([t.pose_world.numpy() for t in tracked])
    gt = np.stack([f.pose.numpy() for f in icl_frames])
    path_length = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    assert ate_rmse(est, gt) < 0.01 * path_length
    # each submap has its own scale (1 / median depth of its first frame); the overlap fit must undo it
    scales = np.cbrt(np.linalg.det(est[:, :3, :3]))
    assert scales.max() / scales.min() > 1.2


def test_submaps_overlap_by_one_frame_and_close_with_their_state(icl_frames):
    tracker = SubmapTracker(OracleModel(icl_frames), TrackerConfig(submap_length=8))
    tracked = _run(tracker, icl_frames, range(22))
    assert [t.submap_id for t in tracked] == [0] * 7 + [1] * 7 + [2] * 7 + [3]
    finished = tracker.pop_finished_submaps()
    assert [f.submap_id for f in finished] == [0, 1, 2]
    assert finished[1].frame_ids == list(range(7, 14))
    assert finished[0].state.frames_seen == 8  # the overlap frame 7 was also the 8th frame of submap 0
    assert tracker.pop_finished_submaps() == []
    for t in tracked:
        if t.index in (0, 7, 14, 21):
            assert t.is_keyframe and t.keyframe_id == t.index
            np.testing.assert_allclose(t.pose_submap.numpy(), np.eye(4), atol=1e-6)
    links = tracker.inter_submap_constraints()
    assert [(e.j) for e in links] == [7, 14, 21]
    # the overlap scale is the ratio of the two submaps' depth normalisations
    d = [icl_frames[n].depth for n in (0, 7)]
    expected = float(d[1][d[1] > 0].median() / d[0][d[0] > 0].median())
    assert tracker.overlap_scales[0] == pytest.approx(expected, rel=1e-3)


def test_constraints_chain_all_keyframes_consistently(icl_frames):
    tracker = SubmapTracker(OracleModel(icl_frames), TrackerConfig(submap_length=8, keyframe_rotation_deg=5))
    tracked = _run(tracker, icl_frames, range(30))
    keyframes = [t.index for t in tracked if t.is_keyframe]
    assert len(keyframes) > 5  # more than the submap starts alone
    edges = tracker.constraints
    assert [(e.i, e.j) for e in edges] == list(zip(keyframes[:-1], keyframes[1:]))
    poses = tracker.keyframe_poses()
    for e in edges:
        np.testing.assert_allclose(e.relative, relative_transform(poses[e.i], poses[e.j]).numpy(), atol=1e-9)
    for t in tracked:
        assert t.keyframe_id in poses and t.keyframe_id <= t.index
    points, conf = tracker.keyframe_points(keyframes[2])
    assert points.shape == (120, 160, 3) and conf.shape == (120, 160)


def test_snapshot_resumes_mid_submap_exactly(icl_frames):
    model = OracleModel(icl_frames, rotation_drift=0.01)
    straight = _run(SubmapTracker(model), icl_frames, range(26))
    first = SubmapTracker(model)
    _run(first, icl_frames, range(11))
    resumed = SubmapTracker(model)
    resumed.load_bytes(first.to_bytes())
    rest = _run(resumed, icl_frames, range(11, 26))
    for a, b in zip(straight[11:], rest):
        assert (a.submap_id, a.is_keyframe) == (b.submap_id, b.is_keyframe)
        np.testing.assert_allclose(a.pose_world.numpy(), b.pose_world.numpy(), atol=1e-5)
    assert [f.submap_id for f in resumed.pop_finished_submaps()] == [0, 1, 2]


def test_relative_scale_is_robust_to_outliers():
    g = torch.Generator().manual_seed(0)
    source = torch.rand(2000, 3, generator=g) + torch.tensor([0, 0, 1.0])
    target = 2.5 * source * (1 + 0.01 * torch.randn(2000, 1, generator=g))
    target[:400] *= 3.0  # 20% gross outliers
    assert relative_scale(target, source) == pytest.approx(2.5, rel=0.02)
    weights = torch.ones(2000)
    weights[:400] = 0.0
    assert relative_scale(target, source, weights) == pytest.approx(2.5, rel=0.005)
    with pytest.raises(ValueError, match="valid point pairs"):
        relative_scale(target[:5], source[:5])


def test_bad_input_is_rejected(icl_frames):
    tracker = SubmapTracker(OracleModel(icl_frames))
    with pytest.raises(ValueError, match=r"\[1,3,H,W\]"):
        tracker.track(0, icl_frames[0].image[0])
    with pytest.raises(ValueError, match="submap_length"):
        TrackerConfig(submap_length=1)
    with pytest.raises(ValueError, match="not a keyframe"):
        tracker.keyframe_points(3)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Many small tensor ops: a 2-thread pool on the shared 2-core machine mostly waits."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def test_uncalibrated_frames_get_intrinsics_estimated_from_the_point_map(icl_frames):
    tracker = SubmapTracker(OracleModel(icl_frames), TrackerConfig(submap_length=4))
    tracked = [tracker.track(n, icl_frames[n].image) for n in range(5)]
    truth = icl_frames[0].intrinsics
    for t in tracked:
        assert (t.intrinsics.width, t.intrinsics.height) == (truth.width, truth.height)
        assert t.intrinsics.fx == pytest.approx(truth.fx, rel=0.01)
    given = tracker.track(5, icl_frames[5].image, truth)
    assert given.intrinsics == truth


class _NoisyPoseHead:
    """The oracle with its pose output (only) perturbed: the point maps still encode the true poses."""

    def __init__(self, oracle: OracleModel, noise: float) -> None:
        self.oracle = oracle
        self.noise = noise
        self.generator = torch.Generator().manual_seed(3)

    def init_state(self, batch: int = 1):
        return self.oracle.init_state(batch)

    def step(self, image, state, update: bool = True):
        from dataclasses import replace

        from worker.geometry import se3_exp

        out = self.oracle.step(image, state, update)
        twist = (torch.randn(6, generator=self.generator) * self.noise).double()
        return replace(out, pose_c2w=(out.pose_c2w[0].double() @ se3_exp(twist)).float()[None])


def test_pointmap_pose_recovers_a_rigid_motion_and_down_weights_outliers():
    from worker.frontend.tracker import pointmap_pose
    from worker.geometry import se3_exp

    g = torch.Generator().manual_seed(0)
    cam = torch.rand(24, 32, 3, generator=g) * torch.tensor([2.0, 2.0, 3.0]) + torch.tensor([-1.0, -1.0, 1.0])
    c2w = se3_exp(torch.tensor([0.3, -0.1, 0.2, 0.05, 0.2, -0.1], dtype=torch.float64))
    world = (cam.double() @ c2w[:3, :3].T + c2w[:3, 3]).float()
    weights = torch.ones(24, 32)
    assert torch.allclose(pointmap_pose(cam, world, weights), c2w, atol=1e-5)
    world[:4] += 5.0  # four rows of wild points, nearly zero weight
    weights[:4] = 1e-6
    assert torch.allclose(pointmap_pose(cam, world, weights), c2w, atol=1e-4)
    assert not torch.allclose(pointmap_pose(cam, world, torch.ones(24, 32)), c2w, atol=1e-2)
    with pytest.raises(ValueError, match="at least 3 valid"):
        pointmap_pose(cam, world, torch.zeros(24, 32))


def test_pointmap_pose_source_ignores_a_wrong_pose_head(icl_frames):
    with pytest.raises(ValueError, match="pose_source"):
        TrackerConfig(pose_source="imu")
    gt = np.stack([f.pose.numpy() for f in icl_frames])
    ate = {}
    for source in ("head", "pointmap"):
        model = _NoisyPoseHead(OracleModel(icl_frames), noise=0.05)
        tracker = SubmapTracker(model, TrackerConfig(submap_length=6, pose_source=source))
        tracked = _run(tracker, icl_frames, range(len(icl_frames)))
        ate[source] = ate_rmse(np.stack([t.pose_world.numpy() for t in tracked]), gt)
    assert ate["pointmap"] < 1e-3 < 0.01 < ate["head"]
    restored = SubmapTracker(OracleModel(icl_frames))
    restored.load_bytes(tracker.to_bytes())
    assert restored.config.pose_source == "pointmap"
