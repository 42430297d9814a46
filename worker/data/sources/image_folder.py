"""A folder of images (jpg/png), in natural filename order; an optional intrinsics.json beside them."""

from __future__ import annotations

from pathlib import Path

from .base import DatasetError, FrameRecord, RecordedSource, SourceOptions, list_images, read_intrinsics_json


class ImageFolderSource(RecordedSource):
    """Every image in `folder`; timestamps are index / fps. The camera comes from `folder/intrinsics.json`
    (fx, fy, cx, cy, width, height) or the `intrinsics` option; otherwise it is unknown (None)."""

    def __init__(self, folder: str | Path, options: SourceOptions, fps: float = 30.0) -> None:
        folder = Path(folder)
        if not folder.is_dir():
            raise DatasetError(f"image folder not found: {folder}")
        if fps <= 0:
            raise DatasetError(f"fps must be positive, got {fps}")
        images = list_images(folder)
        if not images:
            raise DatasetError(f"no .jpg/.jpeg/.png images in {folder}")
        intrinsics_file = folder / "intrinsics.json"
        intrinsics = read_intrinsics_json(intrinsics_file)[0] if intrinsics_file.is_file() else None
        records = [FrameRecord(i / fps, path) for i, path in enumerate(images)]
        super().__init__(folder.name, records, intrinsics, None, options)
