"""Frame sources: `open_source(path_or_uri, **options)` picks the reader for a video, an image folder, a dataset
folder (TUM RGB-D, ICL/Open3D, Replica, ScanNet, KITTI odometry, a photo capture with a transforms.json) or a
`synthetic://` URI."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .base import DatasetError, FrameRecord, FrameSource, RecordedSource, SourceOptions
from .icl import IclSource
from .image_folder import ImageFolderSource
from .kitti import KittiOdometrySource
from .replica import ReplicaSource
from .scannet import ScanNetSource
from .transforms import TransformsJsonSource
from .tum import TumRgbdSource
from .video import VIDEO_SUFFIXES, VideoSource

FORMATS = ("video", "images", "tum", "icl", "replica", "scannet", "kitti", "transforms", "synthetic")
_COMMON_KEYS = {"stride", "max_frames", "resize", "use_gt_poses", "use_gt_depth", "intrinsics"}


def detect_format(path: Path) -> str:
    """The format name of a file or folder, by its layout. Raises DatasetError when nothing matches."""
    if not path.exists():
        raise DatasetError(f"no such file or folder: {path}")
    if path.is_file():
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return "video"
        raise DatasetError(f"{path} is a file but not a video ({', '.join(VIDEO_SUFFIXES)})")
    if (path / "rgb.txt").is_file():
        return "tum"
    if (path / "results").is_dir() and (path / "traj.txt").is_file():
        return "replica"
    if (path / "color").is_dir() and (path / "intrinsic").is_dir():
        return "scannet"
    if (path / "calib.txt").is_file() and ((path / "image_2").is_dir() or (path / "image_0").is_dir()):
        return "kitti"
    if (path / "intrinsics.json").is_file() and any((path / d).is_dir() for d in ("image", "rgb", "color")):
        return "icl"
    if (path / "transforms.json").is_file():
        return "transforms"
    if any(p.suffix.lower() in (".jpg", ".jpeg", ".png") for p in path.iterdir()):
        return "images"
    raise DatasetError(
        f"cannot tell the format of {path}: expected a video, an image folder, or a TUM (rgb.txt), Replica "
        "(results/ + traj.txt), ScanNet (color/ + intrinsic/), KITTI (calib.txt + image_2/), ICL "
        "(intrinsics.json + image/) or photo-capture (transforms.json) folder"
    )


def open_source(path_or_uri: str | Path, format: str | None = None, **options: Any) -> FrameSource:
    """Open any supported frame source.

    Common options: stride, max_frames, resize=(width, height), use_gt_poses (copy ground truth into Frame.pose),
    use_gt_depth (attach depth, default True), intrinsics (override the camera), pingpong=N (a dataset folder played
    forward and back N sweeps, `PingPongSource`), scale=s (every pose and depth multiplied by s: the same scene in
    other length units, `ScaledSource`). Format-specific options are passed on (e.g. fps for image folders,
    max_difference for TUM, poses_file for KITTI). `format` forces a reader.
    """
    sweeps = options.pop("pingpong", None)
    scale = options.pop("scale", None)
    source = _open(path_or_uri, format, **options)
    if sweeps is not None and int(sweeps) != 1:
        from .pingpong import PingPongSource

        source = PingPongSource(source, int(sweeps))
    if scale is not None and float(scale) != 1.0:
        from .scaled import ScaledSource

        source = ScaledSource(source, float(scale))
    return source


def _open(path_or_uri: str | Path, format: str | None, **options: Any) -> FrameSource:
    text = str(path_or_uri)
    if format is None and text.startswith("synthetic://"):
        format = "synthetic"
    common = {k: options.pop(k) for k in list(options) if k in _COMMON_KEYS}
    if common.get("resize") is not None:
        common["resize"] = tuple(common["resize"])
    source_options = SourceOptions(**common)
    if format == "synthetic":
        from worker.data.synthetic import open_synthetic_uri

        return open_synthetic_uri(text, source_options, **options)
    path = Path(text)
    format = format or detect_format(path)
    readers = {
        "video": VideoSource, "images": ImageFolderSource, "tum": TumRgbdSource, "icl": IclSource,
        "replica": ReplicaSource, "scannet": ScanNetSource, "kitti": KittiOdometrySource,
        "transforms": TransformsJsonSource,
    }
    if format not in readers:
        raise DatasetError(f"unknown format {format!r}; known: {', '.join(FORMATS)}")
    if not path.exists():
        raise DatasetError(f"no such file or folder: {path}")
    try:
        return readers[format](path, source_options, **options)
    except TypeError as exc:
        raise DatasetError(f"bad option for the {format} reader: {exc}") from exc


__all__ = [
    "FORMATS", "DatasetError", "FrameRecord", "FrameSource", "IclSource", "ImageFolderSource",
    "KittiOdometrySource", "RecordedSource", "ReplicaSource", "ScanNetSource", "SourceOptions", "TransformsJsonSource",
    "TumRgbdSource",
    "VideoSource", "detect_format", "open_source",
]
