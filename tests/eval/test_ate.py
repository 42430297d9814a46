"""ATE after Sim(3)/SE(3) alignment, checked against evo (the tool the SLAM papers use) and known transforms."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from worker.eval import Trajectory, absolute_trajectory_error, read_tum, write_tum
from worker.geometry import so3_exp


def random_trajectory(rng: np.random.Generator, n: int = 80) -> np.ndarray:
    """A smooth-ish random walk of camera-to-world poses [n, 4, 4]."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    position, rotation = np.zeros(3), np.eye(3)
    for i in range(n):
        position = position + rng.normal(0, 0.05, 3) + np.array([0.03, 0.0, 0.01])
        rotation = rotation @ so3_exp(torch.from_numpy(rng.normal(0, 0.05, 3))).numpy()
        poses[i, :3, :3], poses[i, :3, 3] = rotation, position
    return poses


def similarity(rng: np.random.Generator, scale: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = scale * so3_exp(torch.from_numpy(rng.normal(0, 1.0, 3))).numpy()
    T[:3, 3] = rng.normal(0, 2.0, 3)
    return T


@pytest.fixture
def noisy_pair(tmp_path: Path) -> tuple[Path, Path]:
    """Reference and estimate TUM files: estimate = unknown Sim(3) of the reference plus noise, offset stamps."""
    rng = np.random.default_rng(7)
    reference = random_trajectory(rng)
    stamps = 1000.0 + np.arange(len(reference)) / 30.0
    S = similarity(rng, scale=0.37)
    estimate = S @ reference
    estimate[:, :3, 3] += rng.normal(0, 0.02, (len(reference), 3))
    ref_path, est_path = tmp_path / "ref.txt", tmp_path / "est.txt"
    write_tum(ref_path, Trajectory(stamps, reference))
    # The estimate misses a few frames and its stamps jitter by 2 ms: association must cope.
    keep = np.setdiff1d(np.arange(len(reference)), [3, 17, 40])
    write_tum(est_path, Trajectory(stamps[keep] + 0.002, estimate[keep]))
    return ref_path, est_path


def evo_cli_rmse(ref: Path, est: Path, *flags: str) -> float:
    """The RMSE `evo_ape tum ref est <flags>` saves (full precision, from its results archive)."""
    exe = str(Path(sys.executable).with_name("evo_ape"))
    if not Path(exe).exists():
        exe = shutil.which("evo_ape") or pytest.skip("evo_ape is not installed")
    results = ref.parent / "evo_results.zip"
    env = dict(os.environ, MPLBACKEND="Agg", HOME=str(ref.parent))
    out = subprocess.run([exe, "tum", str(ref), str(est), *flags, "--save_results", str(results)],
                         capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    with zipfile.ZipFile(results) as archive:
        return float(json.loads(archive.read("stats.json"))["rmse"])


def test_sim3_ate_matches_evo_ape_cli(noisy_pair):
    pytest.importorskip("evo")
    ref_path, est_path = noisy_pair
    ours = absolute_trajectory_error(read_tum(est_path), read_tum(ref_path), align="sim3")
    assert ours.num_poses == 77
    expected = evo_cli_rmse(ref_path, est_path, "-as")
    assert ours.rmse == pytest.approx(expected, rel=1e-6)
    assert 0.02 < ours.rmse < 0.2  # the injected noise (scaled back by 1 / 0.37), not zero, not unaligned


def test_se3_ate_matches_evo_api(noisy_pair):
    evo_sync = pytest.importorskip("evo.core.sync")
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    def load(path: Path) -> PoseTrajectory3D:  # np.loadtxt, not our reader: evo sees the file independently
        rows = np.loadtxt(path)
        return PoseTrajectory3D(positions_xyz=rows[:, 1:4], orientations_quat_wxyz=rows[:, [7, 4, 5, 6]],
                                timestamps=rows[:, 0])

    ref_path, est_path = noisy_pair
    ref, est = load(ref_path), load(est_path)
    ref, est = evo_sync.associate_trajectories(ref, est, max_diff=0.01)
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ours = absolute_trajectory_error(read_tum(est_path), read_tum(ref_path), align="se3")
    assert ours.rmse == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
    assert ours.scale == pytest.approx(1.0)
    # Without the scale correction the error is far larger than the injected 2 cm noise.
    assert ours.rmse > 0.2


def test_sim3_alignment_recovers_exact_similarity():
    rng = np.random.default_rng(3)
    reference = random_trajectory(rng, 40)
    S = similarity(rng, scale=2.5)
    result = absolute_trajectory_error(S @ reference, reference, align="sim3")
    assert result.rmse < 1e-9
    assert result.scale == pytest.approx(1 / 2.5, rel=1e-9)
    np.testing.assert_allclose(result.alignment @ S, np.eye(4), atol=1e-9)


def test_no_alignment_reports_raw_error():
    reference = np.zeros((10, 3))
    estimate = reference + np.array([0.0, 3.0, 4.0])
    result = absolute_trajectory_error(estimate, reference, align="none")
    assert result.rmse == pytest.approx(5.0)
    assert result.max == pytest.approx(5.0)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="align must be"):
        absolute_trajectory_error(np.zeros((5, 3)), np.zeros((5, 3)), align="affine")
    with pytest.raises(ValueError, match="pair up"):
        absolute_trajectory_error(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match="at least 3"):
        absolute_trajectory_error(np.zeros((2, 3)), np.zeros((2, 3)))
    far = Trajectory(np.arange(5) + 100.0, np.tile(np.eye(4), (5, 1, 1)))
    near = Trajectory(np.arange(5) * 1.0, np.tile(np.eye(4), (5, 1, 1)))
    with pytest.raises(ValueError, match="no timestamps"):
        absolute_trajectory_error(far, near)
