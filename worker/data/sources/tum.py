"""TUM RGB-D benchmark sequences: rgb.txt, depth.txt, groundtruth.txt associated by timestamp."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from worker.data.tum_trajectory import associate, poses_from_tum_rows
from worker.geometry import Intrinsics

from .base import DatasetError, FrameRecord, RecordedSource, SourceOptions, load_matrix_rows, read_intrinsics_json

# Calibrations published with the benchmark (640x480); the ROS default is used for unknown sequences.
TUM_CAMERAS = {
    "freiburg1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    "freiburg2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    "freiburg3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}
TUM_DEFAULT_CAMERA = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
TUM_DEPTH_SCALE = 5000.0  # depth png units per metre


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Timestamps and file names of a TUM list file (`timestamp filename` per line)."""
    if not path.is_file():
        raise DatasetError(f"TUM list file not found: {path}")
    stamps, names = [], []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2:
            raise DatasetError(f"{path}:{line_no}: expected 'timestamp filename'")
        try:
            stamps.append(float(parts[0]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{line_no}: bad timestamp {parts[0]!r}") from exc
        names.append(parts[1])
    return np.asarray(stamps, dtype=np.float64), names


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps [N] and camera-to-world poses [N, 4, 4] of a TUM groundtruth file."""
    rows = load_matrix_rows(path, 8)
    if len(rows) == 0:
        raise DatasetError(f"{path}: no poses")
    try:
        return rows[:, 0], poses_from_tum_rows(rows)
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc


def camera_for_sequence(name: str) -> Intrinsics:
    """The published camera of a TUM sequence, by the freiburgN in its name."""
    for key, camera in TUM_CAMERAS.items():
        if key in name:
            return camera
    return TUM_DEFAULT_CAMERA


class TumRgbdSource(RecordedSource):
    """A TUM RGB-D sequence folder.

    Each rgb frame is paired with the nearest depth frame and ground-truth pose within max_difference seconds
    (one-to-one, as the benchmark's associate.py). With depth requested, rgb frames without a depth partner are
    dropped; frames without a ground-truth partner keep gt_pose=None. The camera: `intrinsics.json` in the folder,
    else the published freiburg1/2/3 calibration by folder name (no undistortion is applied).
    """

    def __init__(self, root: str | Path, options: SourceOptions, max_difference: float = 0.02) -> None:
        root = Path(root)
        rgb_stamps, rgb_names = read_file_list(root / "rgb.txt")
        depth_paths: list[Path | None] = [None] * len(rgb_names)
        keep = np.arange(len(rgb_names))
        if options.use_gt_depth and (root / "depth.txt").is_file():
            depth_stamps, depth_names = read_file_list(root / "depth.txt")
            i, j = associate(rgb_stamps, depth_stamps, max_difference)
            keep = i
            for a, b in zip(i, j):
                depth_paths[a] = root / depth_names[b]
        gt_poses: list[np.ndarray | None] = [None] * len(rgb_names)
        if (root / "groundtruth.txt").is_file():
            gt_stamps, poses = read_groundtruth(root / "groundtruth.txt")
            i, j = associate(rgb_stamps, gt_stamps, max_difference)
            for a, b in zip(i, j):
                gt_poses[a] = poses[b]
        records = [FrameRecord(rgb_stamps[k], root / rgb_names[k], depth_paths[k], gt_poses[k]) for k in keep]
        intrinsics_file = root / "intrinsics.json"
        if intrinsics_file.is_file():
            intrinsics, extra = read_intrinsics_json(intrinsics_file)
            depth_scale = float(extra.get("depth_scale", TUM_DEPTH_SCALE))
        else:
            intrinsics, depth_scale = camera_for_sequence(root.name), TUM_DEPTH_SCALE
        super().__init__(root.name, records, intrinsics, depth_scale, options)
