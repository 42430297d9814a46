"""ICL-NUIM as packaged by Open3D (and tests/data/icl_mini): image/ or rgb/, depth/, trajectory.log or
groundtruth.txt, intrinsics.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import DatasetError, FrameRecord, RecordedSource, SourceOptions, list_images, read_intrinsics_json
from .tum import read_groundtruth


def read_open3d_log(path: Path) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] of an Open3D trajectory .log (a 3-number header line, then 4 matrix rows)."""
    if not path.is_file():
        raise DatasetError(f"trajectory file not found: {path}")
    lines = [line.split() for line in path.read_text().splitlines() if line.strip()]
    if len(lines) % 5:
        raise DatasetError(f"{path}: expected blocks of 5 lines (header + 4x4), got {len(lines)} lines")
    poses = []
    for block in range(0, len(lines), 5):
        try:
            matrix = np.array([[float(v) for v in row] for row in lines[block + 1: block + 5]], dtype=np.float64)
        except ValueError as exc:
            raise DatasetError(f"{path}: bad number in block starting at line {block + 1}: {exc}") from exc
        if matrix.shape != (4, 4):
            raise DatasetError(f"{path}: block starting at line {block + 1} is not a 4x4 matrix")
        poses.append(matrix)
    return np.stack(poses)


class IclSource(RecordedSource):
    """ICL/Open3D layout. Images are sorted by name; frame i pairs with depth/<same stem>.png and the i-th pose.

    Timestamps come from groundtruth.txt when present (its i-th line), else i / fps from intrinsics.json (30).
    Depth units per metre: `depth_scale` in intrinsics.json (default 1000).
    """

    def __init__(self, root: str | Path, options: SourceOptions) -> None:
        root = Path(root)
        image_dir = next((root / d for d in ("image", "rgb", "color") if (root / d).is_dir()), None)
        if image_dir is None:
            raise DatasetError(f"{root}: no image/ or rgb/ folder")
        images = list_images(image_dir)
        if not images:
            raise DatasetError(f"{image_dir}: no images")
        intrinsics, extra = read_intrinsics_json(root / "intrinsics.json")
        fps = float(extra.get("fps", 30.0))
        stamps = np.arange(len(images), dtype=np.float64) / fps
        poses: np.ndarray | None = None
        if (root / "groundtruth.txt").is_file():
            stamps_gt, poses = read_groundtruth(root / "groundtruth.txt")
            stamps = stamps_gt
        elif (root / "trajectory.log").is_file():
            poses = read_open3d_log(root / "trajectory.log")
        if poses is not None and len(poses) != len(images):
            raise DatasetError(f"{root}: {len(images)} images but {len(poses)} poses")
        depth_dir = root / "depth"
        records = []
        for i, image in enumerate(images):
            depth = depth_dir / f"{image.stem}.png"
            records.append(FrameRecord(float(stamps[i]), image, depth if depth_dir.is_dir() else None,
                                       None if poses is None else poses[i]))
        super().__init__(root.name, records, intrinsics, float(extra.get("depth_scale", 1000.0)), options)
