"""TUM trajectory files: round trip, Sim(3) scale handling, association, malformed input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worker.eval import Trajectory, associate, format_tum, read_tum, write_tum
from worker.geometry import so3_exp


def test_round_trip_preserves_poses(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (6, 1, 1))
    for i in range(6):
        poses[i, :3, :3] = so3_exp(torch.from_numpy(rng.normal(0, 1, 3))).numpy()
        poses[i, :3, 3] = rng.normal(0, 1, 3)
    path = tmp_path / "t.txt"
    write_tum(path, Trajectory(np.arange(6) * 0.1 + 5, poses))
    back = read_tum(path)
    np.testing.assert_allclose(back.poses, poses, atol=1e-12)
    np.testing.assert_allclose(back.timestamps, np.arange(6) * 0.1 + 5, atol=1e-9)


def test_sim3_pose_is_written_without_its_scale():
    pose = np.eye(4)
    pose[:3, :3] = 3.0 * so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)).numpy()
    pose[:3, 3] = [1, 2, 3]
    line = format_tum(Trajectory([1.0], pose[None])).splitlines()[1].split()
    q = np.array(line[4:], dtype=float)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    assert [float(v) for v in line[1:4]] == [1.0, 2.0, 3.0]


def test_tum_quaternion_order_is_xyzw(tmp_path):
    path = tmp_path / "q.txt"
    # 90 degrees about z: qx qy qz qw = 0 0 sin45 cos45.
    path.write_text("# comment\n0.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n")
    traj = read_tum(path)
    np.testing.assert_allclose(traj.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(traj.positions[0], [1, 2, 3])


def test_associate_pairs_nearest_within_tolerance_one_to_one():
    first = np.array([0.0, 0.1, 0.2, 0.3])
    second = np.array([0.004, 0.095, 0.098, 0.5])
    i, j = associate(first, second, max_difference=0.01)
    assert i.tolist() == [0, 1] and j.tolist() == [0, 2]


@pytest.mark.parametrize("text, message", [
    ("0 1 2 3 0 0 0\n", "8 numbers"),
    ("0 1 2 x 0 0 0 1\n", ":1:"),
    ("0 0 0 0 0 0 0 0\n", "zero quaternion"),
    ("1 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n", "increasing"),
    ("# only a comment\n", "no poses"),
])
def test_malformed_files_raise_value_error(tmp_path, text, message):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_tum(path)


def test_missing_file_raises(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        read_tum(tmp_path / "nope.txt")
