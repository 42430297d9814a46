"""Replica as distributed with NICE-SLAM: <scene>/results/frame*.jpg + depth*.png, <scene>/traj.txt and
cam_params.json (in the scene folder or its parent)."""

from __future__ import annotations

import json
from pathlib import Path

from worker.geometry import Intrinsics

from .base import DatasetError, FrameRecord, RecordedSource, SourceOptions, list_images, load_matrix_rows

# NICE-SLAM's configs/Replica/replica.yaml camera (1200x680), used when no cam_params.json is found.
REPLICA_DEFAULT_CAMERA = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
REPLICA_DEPTH_SCALE = 6553.5


def read_cam_params(path: Path) -> tuple[Intrinsics, float]:
    """Camera and depth scale from Replica's cam_params.json ({"camera": {w, h, fx, fy, cx, cy, scale}})."""
    try:
        cam = json.loads(path.read_text())["camera"]
        return (Intrinsics(float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]), int(cam["w"]),
                           int(cam["h"])), float(cam.get("scale", REPLICA_DEPTH_SCALE)))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"cannot read Replica camera parameters from {path}: {exc}") from exc


class ReplicaSource(RecordedSource):
    """frame{i:06d}.jpg with depth{i:06d}.png; traj.txt has one row-major camera-to-world 4x4 per line.
    Timestamps: i / fps (30)."""

    def __init__(self, root: str | Path, options: SourceOptions, fps: float = 30.0) -> None:
        root = Path(root)
        results = root / "results"
        if not results.is_dir():
            raise DatasetError(f"{root}: no results/ folder (NICE-SLAM Replica layout)")
        images = list_images(results, prefix="frame")
        if not images:
            raise DatasetError(f"{results}: no frame*.jpg images")
        poses = load_matrix_rows(root / "traj.txt", 16).reshape(-1, 4, 4)
        if len(poses) < len(images):
            raise DatasetError(f"{root}: {len(images)} images but only {len(poses)} poses in traj.txt")
        cam_file = next((p for p in (root / "cam_params.json", root.parent / "cam_params.json") if p.is_file()), None)
        intrinsics, depth_scale = (read_cam_params(cam_file) if cam_file
                                   else (REPLICA_DEFAULT_CAMERA, REPLICA_DEPTH_SCALE))
        records = []
        for i, image in enumerate(images):
            depth = results / ("depth" + image.stem[len("frame"):] + ".png")
            records.append(FrameRecord(i / fps, image, depth if depth.exists() else None, poses[i]))
        super().__init__(root.name, records, intrinsics, depth_scale, options)
