"""Fixtures for the loop-closure tests: the ICL mini frames (downscaled to 160x120) and their overlap oracle."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from worker.geometry import project_points, sim3_apply, unproject_depth
from worker.loop.oracle import load_rgbd_folder


@pytest.fixture(scope="session")
def icl_frames(request):
    return load_rgbd_folder(Path(request.config.rootpath) / "tests" / "data" / "icl_mini", downscale=2)


def ground_truth_overlap(frames, i: int, j: int, depth_tolerance: float = 0.1) -> float:
    """Fraction of frame i's depth points seen by frame j with a consistent depth (from ground truth)."""
    K = frames[i].intrinsics.matrix(torch.float64)
    d = frames[i].depth.double()
    P = unproject_depth(d, K)[d > 0][::4]
    Pj = sim3_apply(torch.linalg.inv(frames[j].pose), sim3_apply(frames[i].pose, P))
    uv, z = project_points(Pj, K)
    H, W = frames[j].depth.shape
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    zj = frames[j].depth.double()[uv[inside, 1].long(), uv[inside, 0].long()]
    good = (zj > 0) & ((z[inside] - zj).abs() < depth_tolerance * zj)
    return float(good.sum()) / max(1, len(P))


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """These tests run many small tensor ops, where a 2-thread pool on a shared 2-core machine mostly waits."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
