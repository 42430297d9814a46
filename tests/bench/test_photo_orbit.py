"""bench.photo_orbit: the object an orbit looks at, each photo's error as a share of its distance, and Middlebury's
ring written as a transforms.json capture in ring order with its upside-down photos turned upright."""

from __future__ import annotations

import json

import cv2
import numpy as np

from bench.photo_orbit import middlebury_ring_to_transforms, orbit_centre, score
from worker.data import open_source


def _looking_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at `centre` looking at `target`."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = np.stack([x, np.cross(z, x), z], axis=1), centre
    return pose


def _ring(n: int, radius: float, target: np.ndarray) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([_looking_at(target + radius * np.array([np.cos(a), 0.3, np.sin(a)]), target) for a in angles])


def test_the_orbit_centre_is_the_point_every_camera_looks_at() -> None:
    target = np.array([0.2, -0.1, 1.5])
    np.testing.assert_allclose(orbit_centre(_ring(12, 2.0, target)), target, atol=1e-9)


def test_a_photo_moved_by_a_tenth_of_its_distance_is_the_one_outside_five_percent() -> None:
    truth = _ring(20, 2.0, np.zeros(3))
    distance = np.linalg.norm(truth[0, :3, 3])
    estimate = truth.copy()
    estimate[:, :3, 3] *= 3.0  # another scale: the Sim(3) alignment takes it out
    estimate[7, :3, 3] += np.array([0.1, 0.0, 0.0]) * distance * 3.0
    values = score(dict(enumerate(estimate)), dict(enumerate(truth)))
    assert values["registered_share"] == 1.0 and values["within_5_percent"] == 19 and values["worst_photo"] == 7
    assert 0.05 < values["worst_share"] < 0.1


def test_a_middlebury_ring_becomes_an_upright_capture_in_ring_order(tmp_path) -> None:
    src, dst = tmp_path / "ring", tmp_path / "capture"
    src.mkdir()
    K = np.array([[100.0, 0, 30.0], [0, 100.0, 20.0], [0, 0, 1]])
    height, width = 48, 64
    lines, angles = ["3"], []
    views = [("b.png", -80.0, 20.0), ("a.png", 80.0, 180.0 + 5.0), ("c.png", -80.0, 60.0)]  # a is upside down at 5
    for name, lat, lon in views:
        image = np.zeros((height, width, 3), np.uint8)
        marker = (int(K[0, 2]) + 10, int(K[1, 2]) - 8) if lat < 0 else (int(K[0, 2]) - 10, int(K[1, 2]) + 8)
        cv2.circle(image, marker, 3, (255, 255, 255), -1)  # 10 px right of and 8 px above the principal point
        cv2.imwrite(str(src / name), image)
        R, t = np.eye(3), np.array([0.0, 0.0, 1.0])
        lines.append(" ".join([name, *map(str, K.ravel()), *map(str, R.ravel()), *map(str, t)]))
        angles.append(f"{lat} {lon} {name}")
    (src / "ring_par.txt").write_text("\n".join(lines) + "\n")
    (src / "ring_ang.txt").write_text("\n".join(angles) + "\n")
    assert middlebury_ring_to_transforms(src, dst) == 3
    frames = json.loads((dst / "transforms.json").read_text())["frames"]
    assert [f["source"] for f in frames] == ["a.png", "b.png", "c.png"]  # 5, 20, 60 degrees round the ring
    upright = cv2.imread(str(dst / frames[0]["file_path"]), cv2.IMREAD_GRAYSCALE)
    rows, cols = np.nonzero(upright > 128)
    assert abs(cols.mean() - (K[0, 2] + 10)) <= 1 and abs(rows.mean() - (K[1, 2] - 8)) <= 1  # as the upright have it
    poses = [f.gt_pose for f in open_source(str(dst), use_gt_depth=False)]
    np.testing.assert_allclose(poses[0][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)  # turned half round
    np.testing.assert_allclose(poses[1][:3, :3], np.eye(3), atol=1e-12)
