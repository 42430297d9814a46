"""PnP + RANSAC loop constraints (the classical second source) on full-resolution ICL frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from worker.frontend.tracker import SubmapTracker, TrackerConfig
from worker.geometry import relative_transform, sim3_decompose, so3_log, unproject_depth
from worker.loop.oracle import OracleModel, load_rgbd_folder
from worker.loop.pnp import PnPRelocalizer


@pytest.fixture(scope="module")
def full_frames(request):
    return load_rgbd_folder(Path(request.config.rootpath) / "tests" / "data" / "icl_mini")


def _tracked_pair(frames, i: int, j: int) -> SubmapTracker:
    """i and j tracked as consecutive frames in two submaps (so j carries another scale than i)."""
    tracker = SubmapTracker(OracleModel(frames), TrackerConfig(submap_length=2))
    for n in (i, j):
        tracker.track(n, frames[n].image, frames[n].intrinsics)
    return tracker


def _errors(constraint, truth: torch.Tensor) -> tuple[float, float, float]:
    s0, R0, t0 = sim3_decompose(truth)
    s, R, t = sim3_decompose(torch.from_numpy(constraint.relative))
    return float(s / s0), float(so3_log(R0.T @ R).norm()), float((t - t0).norm() / t0.norm())


@pytest.mark.parametrize("i,j", [(0, 9), (12, 35), (20, 28)])
def test_pnp_constraint_matches_the_true_similarity(full_frames, i, j):
    tracker = _tracked_pair(full_frames, i, j)
    pnp = PnPRelocalizer(tracker)
    pnp.add_keyframe(i, full_frames[i].image)
    c = pnp.relocalize(i, j, full_frames[j].image, full_frames[j].intrinsics)
    assert c.accepted, c.reason
    poses = tracker.keyframe_poses()
    scale_ratio, rot_err, trans_err = _errors(c, relative_transform(poses[i], poses[j]))
    assert scale_ratio == pytest.approx(1.0, abs=0.02)
    assert rot_err < 0.03 and trans_err < 0.1
    assert c.to_edge().kind == "loop"


def test_given_depth_points_can_replace_predictions(full_frames):
    i, j = 0, 9
    tracker = _tracked_pair(full_frames, i, j)
    K = full_frames[i].intrinsics.matrix(torch.float64)
    metric = {i: unproject_depth(full_frames[i].depth.double(), K).float()}
    pnp = PnPRelocalizer(tracker, points_of=metric.__getitem__)
    pnp.add_keyframe(i, full_frames[i].image)
    c = pnp.relocalize(i, j, full_frames[j].image, full_frames[j].intrinsics)
    assert c.accepted
    # metric points: the constraint's translation is metric (same as ground truth between the two cameras)
    truth_metric = relative_transform(full_frames[i].pose, full_frames[j].pose)
    _, R, t = sim3_decompose(torch.from_numpy(c.relative))
    assert float(so3_log(truth_metric[:3, :3].T @ R).norm()) < 0.03
    assert float((t - truth_metric[:3, 3]).norm()) < 0.1 * float(truth_metric[:3, 3].norm())


def test_wide_baseline_without_reliable_matches_is_rejected_not_guessed(full_frames):
    tracker = _tracked_pair(full_frames, 6, 62)
    pnp = PnPRelocalizer(tracker)
    pnp.add_keyframe(6, full_frames[6].image)
    c = pnp.relocalize(6, 62, full_frames[62].image, full_frames[62].intrinsics)
    assert not c.accepted and c.reason
    np.testing.assert_allclose(c.relative, np.eye(4))
    with pytest.raises(ValueError, match="no ORB features"):
        pnp.relocalize(3, 62, full_frames[62].image, full_frames[62].intrinsics)
