"""ScanNet as exported by its SensReader: color/<i>.jpg, depth/<i>.png (mm), pose/<i>.txt, intrinsic/*.txt."""

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
    read_depth,
    valid_pose,
)

SCANNET_DEPTH_SCALE = 1000.0


def read_intrinsic_matrix(path: Path, width: int, height: int) -> Intrinsics:
    """A ScanNet intrinsic_*.txt (4x4 or 3x3 K) for an image of width x height."""
    if not path.is_file():
        raise DatasetError(f"intrinsics file not found: {path}")
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc
    if values.size not in (9, 16):
        raise DatasetError(f"{path}: expected a 3x3 or 4x4 intrinsic matrix, got {values.size} numbers")
    K = values.reshape(3, 3) if values.size == 9 else values.reshape(4, 4)
    return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)


class ScanNetSource(RecordedSource):
    """A ScanNet scene export. Timestamps: i / fps (30). Poses with -inf (lost tracking) give gt_pose=None.

    When depth is present its resolution (640x480) is the native size, as in NICE-SLAM/MonoGS: colour is resized to
    it and the depth camera's intrinsics (intrinsic_depth.txt) are used. Without depth, colour keeps its own size
    and intrinsic_color.txt.
    """

    def __init__(self, root: str | Path, options: SourceOptions, fps: float = 30.0) -> None:
        root = Path(root)
        for sub in ("color", "intrinsic"):
            if not (root / sub).is_dir():
                raise DatasetError(f"{root}: no {sub}/ folder (ScanNet export layout)")
        images = list_images(root / "color")
        if not images:
            raise DatasetError(f"{root / 'color'}: no images")
        records = []
        for i, image in enumerate(images):
            depth = root / "depth" / f"{image.stem}.png"
            pose_file = root / "pose" / f"{image.stem}.txt"
            pose = valid_pose(load_matrix_rows(pose_file, 4)) if pose_file.is_file() else None
            if pose is not None and pose.shape != (4, 4):
                raise DatasetError(f"{pose_file}: expected a 4x4 matrix")
            records.append(FrameRecord(i / fps, image, depth if depth.is_file() else None, pose))
        use_depth_camera = options.use_gt_depth and records[0].depth_path is not None
        if use_depth_camera:
            height, width = read_depth(records[0].depth_path, 1.0).shape
            intrinsics = read_intrinsic_matrix(root / "intrinsic" / "intrinsic_depth.txt", width, height)
            image_size = (width, height)
        else:
            image_size = image_size_of(images[0])
            intrinsics = read_intrinsic_matrix(root / "intrinsic" / "intrinsic_color.txt", *image_size)
            records = [FrameRecord(r.timestamp, r.image_path, None, r.gt_pose) for r in records]
        super().__init__(root.name, records, intrinsics, SCANNET_DEPTH_SCALE, options, image_size=image_size)

