"""KITTI odometry: sequences/<seq>/image_2 (or image_0), calib.txt, times.txt; poses/<seq>.txt."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from worker.geometry import Intrinsics

from .base import (
    DatasetError,
    FrameRecord,
    RecordedSource,
    SourceOptions,
    image_size_of,
    list_images,
    load_matrix_rows,
)


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """Projection matrices of calib.txt ({'P0': 3x4, ..., 'Tr': 3x4})."""
    if not path.is_file():
        raise DatasetError(f"KITTI calibration not found: {path}")
    matrices = {}
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if ":" not in line:
            continue
        key, values = line.split(":", 1)
        try:
            numbers = np.array(values.split(), dtype=np.float64)
        except ValueError as exc:
            raise DatasetError(f"{path}:{line_no}: {exc}") from exc
        if numbers.size != 12:
            raise DatasetError(f"{path}:{line_no}: {key.strip()} must have 12 numbers, got {numbers.size}")
        matrices[key.strip()] = numbers.reshape(3, 4)
    return matrices


def find_poses_file(root: Path) -> Path | None:
    """poses.txt in the sequence folder, or the benchmark's dataset/poses/<seq>.txt next to sequences/."""
    for candidate in (root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"):
        if candidate.is_file():
            return candidate
    return None


class KittiOdometrySource(RecordedSource):
    """A KITTI odometry sequence, left colour camera (image_2; image_0 grey as a fallback).

    Ground truth (cam0 poses, row-major 3x4 per line) is moved to the camera used: T_w_cam2 = T_w_cam0 * T_cam0_cam2,
    where calib's P2 = K [I | b] gives T_cam0_cam2 = [I | -b]. No depth (KITTI odometry has none).
    """

    def __init__(self, root: str | Path, options: SourceOptions, poses_file: str | Path | None = None) -> None:
        root = Path(root)
        camera = next((c for c in ("image_2", "image_0") if (root / c).is_dir()), None)
        if camera is None:
            raise DatasetError(f"{root}: no image_2/ or image_0/ folder (KITTI odometry layout)")
        images = list_images(root / camera)
        if not images:
            raise DatasetError(f"{root / camera}: no images")
        P = read_calib(root / "calib.txt").get("P" + camera[-1])
        if P is None:
            raise DatasetError(f"{root / 'calib.txt'}: no P{camera[-1]} matrix")
        fx, fy, cx, cy = P[0, 0], P[1, 1], P[0, 2], P[1, 2]
        baseline = np.array([(P[0, 3] - cx * P[2, 3]) / fx, (P[1, 3] - cy * P[2, 3]) / fy, P[2, 3]])
        cam0_to_cam = np.eye(4)
        cam0_to_cam[:3, 3] = -baseline
        stamps = (load_matrix_rows(root / "times.txt", 1)[:, 0] if (root / "times.txt").is_file()
                  else np.arange(len(images)) / 10.0)
        if len(stamps) < len(images):
            raise DatasetError(f"{root}: {len(images)} images but {len(stamps)} timestamps")
        poses_path = Path(poses_file) if poses_file else find_poses_file(root)
        poses = None
        if poses_path is not None:
            rows = load_matrix_rows(poses_path, 12)
            if len(rows) < len(images):
                raise DatasetError(f"{poses_path}: {len(rows)} poses for {len(images)} images")
            poses = np.tile(np.eye(4), (len(rows), 1, 1))
            poses[:, :3, :] = rows.reshape(-1, 3, 4)
            poses = poses @ cam0_to_cam
        records = [FrameRecord(float(stamps[i]), image, None, None if poses is None else poses[i])
                   for i, image in enumerate(images)]
        width, height = image_size_of(images[0])
        super().__init__(root.name, records, Intrinsics(fx, fy, cx, cy, width, height), None, options,
                         image_size=(width, height))
