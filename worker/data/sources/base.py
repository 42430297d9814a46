"""The FrameSource contract and the machinery every dataset reader shares.

A source yields `Frame`s in order. `Frame.index` is the position in the yielded stream (0, 1, 2, ... after stride
and max_frames are applied); `Frame.timestamp` is the dataset's own time in seconds, so results can be matched to
ground truth by timestamp. Ground-truth poses are camera-to-world 4x4 (OpenCV camera axes) and go into
`Frame.gt_pose`; `Frame.pose` is filled only in posed mode (`use_gt_poses=True`). Depth (metres, 0 = invalid) is
attached when the dataset has it and `use_gt_depth=True` (the default).
"""

from __future__ import annotations

import json
import re
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics


class DatasetError(ValueError):
    """A dataset is missing files, has malformed files, or the options given to read it are invalid."""


@dataclass(frozen=True)
class SourceOptions:
    """What every source accepts.

    stride: keep every stride-th frame. max_frames: stop after this many yielded frames. resize: (width, height) of
    the yielded images; intrinsics and depth are resized with them (depth by nearest neighbour, so no invalid/valid
    mixing at edges). use_gt_poses: copy ground truth into Frame.pose (posed mode). use_gt_depth: attach depth.
    intrinsics: override the dataset's camera (given for the dataset's native image size).
    """

    stride: int = 1
    max_frames: int | None = None
    resize: tuple[int, int] | None = None
    use_gt_poses: bool = False
    use_gt_depth: bool = True
    intrinsics: Intrinsics | None = None

    def __post_init__(self) -> None:
        if int(self.stride) != self.stride or self.stride < 1:
            raise DatasetError(f"stride must be an integer >= 1, got {self.stride!r}")
        if self.max_frames is not None and (int(self.max_frames) != self.max_frames or self.max_frames < 1):
            raise DatasetError(f"max_frames must be an integer >= 1 or None, got {self.max_frames!r}")
        if self.resize is not None:
            if len(self.resize) != 2 or any(int(v) != v or v < 1 for v in self.resize):
                raise DatasetError(f"resize must be (width, height) with positive integers, got {self.resize!r}")
            object.__setattr__(self, "resize", (int(self.resize[0]), int(self.resize[1])))
        if self.intrinsics is not None and not isinstance(self.intrinsics, Intrinsics):
            raise DatasetError(f"intrinsics must be an Intrinsics, got {type(self.intrinsics).__name__}")

    def selected(self, count: int) -> range:
        """Positions (in the dataset's order) of the frames these options keep, out of `count`."""
        kept = range(0, count, self.stride)
        return kept if self.max_frames is None else kept[: self.max_frames]


class FrameSource(ABC):
    """An ordered stream of frames with optional camera, depth and ground truth.

    Attributes: name (a short label for logs and tables), intrinsics (for the yielded image size, or None when
    unknown). len() works when the number of frames is known in advance.
    """

    name: str
    intrinsics: Intrinsics | None

    def __init__(self, options: SourceOptions) -> None:
        self.options = options

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]: ...

    def __len__(self) -> int:
        raise TypeError(f"{type(self).__name__} {self.name!r} does not know its length in advance")

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


@dataclass(frozen=True)
class FrameRecord:
    """Where one frame of an on-disk dataset lives. gt_pose: camera-to-world or None when unknown/invalid."""

    timestamp: float
    image_path: Path
    depth_path: Path | None = None
    gt_pose: np.ndarray | None = None


class RecordedSource(FrameSource):
    """A dataset already resolved into a list of FrameRecords, a camera and a depth scale (units per metre)."""

    def __init__(
        self,
        name: str,
        records: Sequence[FrameRecord],
        native_intrinsics: Intrinsics | None,
        depth_scale: float | None,
        options: SourceOptions,
        *,
        image_size: tuple[int, int] | None = None,
    ) -> None:
        super().__init__(options)
        if not records:
            raise DatasetError(f"{name}: no frames found")
        self.name = name
        self._records = [records[i] for i in options.selected(len(records))]
        self._depth_scale = depth_scale
        native = options.intrinsics or native_intrinsics
        # The image size the records decode to (width, height); read once so len/intrinsics need no iteration.
        self._native_size = image_size or image_size_of(self._records[0].image_path)
        if native is not None and (native.width, native.height) != self._native_size:
            native = native.scaled(*self._native_size)
        self._native_intrinsics = native
        size = options.resize or self._native_size
        self.intrinsics = None if native is None else native.scaled(*size)

    def __len__(self) -> int:
        return len(self._records)

    @property
    def records(self) -> list[FrameRecord]:
        """The selected records (after stride and max_frames)."""
        return list(self._records)

    def __iter__(self) -> Iterator[Frame]:
        for index, record in enumerate(self._records):
            yield self._load(index, record)

    def _load(self, index: int, record: FrameRecord) -> Frame:
        image = read_rgb(record.image_path)
        if (image.shape[1], image.shape[0]) != self._native_size:
            image = cv2.resize(image, self._native_size, interpolation=cv2.INTER_AREA)
        depth = None
        if self.options.use_gt_depth and record.depth_path is not None:
            depth = read_depth(record.depth_path, self._depth_scale or 1.0)
            if depth.shape != image.shape[:2]:
                depth = cv2.resize(depth, self._native_size, interpolation=cv2.INTER_NEAREST)
        return finish_frame(index, record.timestamp, image, self._native_intrinsics, depth, record.gt_pose,
                            self.options)


def finish_frame(
    index: int,
    timestamp: float,
    image: np.ndarray,
    intrinsics: Intrinsics | None,
    depth: np.ndarray | None,
    gt_pose: np.ndarray | None,
    options: SourceOptions,
) -> Frame:
    """Apply resize and posed mode to one decoded frame and build the Frame."""
    if options.resize is not None and (image.shape[1], image.shape[0]) != options.resize:
        shrink = options.resize[0] < image.shape[1]
        image = cv2.resize(image, options.resize, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        if depth is not None:
            depth = cv2.resize(depth, options.resize, interpolation=cv2.INTER_NEAREST)
        if intrinsics is not None:
            intrinsics = intrinsics.scaled(*options.resize)
    gt = None if gt_pose is None else np.array(gt_pose, dtype=np.float64)
    pose = gt.copy() if (options.use_gt_poses and gt is not None) else None
    return Frame(index=index, timestamp=float(timestamp), image=np.ascontiguousarray(image), intrinsics=intrinsics,
                 depth=depth, pose=pose, gt_pose=gt)


def read_rgb(path: Path) -> np.ndarray:
    """An image file as uint8 RGB [H, W, 3] (grey images are replicated to three channels)."""
    if not path.is_file():
        raise DatasetError(f"image file not found: {path}")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DatasetError(f"cannot decode image {path} (corrupt or not an image)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, scale: float) -> np.ndarray:
    """A 16-bit (or float) depth image as metres float32 [H, W]; `scale` is stored units per metre."""
    if not path.is_file():
        raise DatasetError(f"depth file not found: {path}")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f"cannot decode depth image {path} (corrupt or not an image)")
    if raw.ndim != 2:
        raise DatasetError(f"depth image {path} must have one channel, got shape {raw.shape}")
    depth = raw.astype(np.float32) / np.float32(scale)
    depth[~np.isfinite(depth)] = 0.0
    return depth


def image_size_of(path: Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    image = read_rgb(path)
    return image.shape[1], image.shape[0]


def natural_key(path: Path) -> tuple:
    """Sort key that orders frame2 before frame10."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name))


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def list_images(folder: Path, prefix: str = "") -> list[Path]:
    """Image files in `folder` whose names start with `prefix`, in natural order."""
    return sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.name.startswith(prefix)),
        key=natural_key,
    )


def read_intrinsics_json(path: Path) -> tuple[Intrinsics, dict]:
    """Intrinsics from a JSON file with fx, fy, cx, cy, width, height (plus any extra keys, returned as a dict)."""
    try:
        data = json.loads(path.read_text())
        return Intrinsics.from_dict(data), data
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"cannot read intrinsics from {path}: {exc}") from exc


def load_matrix_rows(path: Path, columns: int) -> np.ndarray:
    """Whitespace-separated numbers, `columns` per row, '#' comments skipped, as float64 [N, columns]."""
    if not path.is_file():
        raise DatasetError(f"file not found: {path}")
    rows = []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != columns:
            raise DatasetError(f"{path}:{line_no}: expected {columns} numbers, got {len(parts)}")
        try:
            rows.append([float(v) for v in parts])
        except ValueError as exc:
            raise DatasetError(f"{path}:{line_no}: {exc}") from exc
    return np.asarray(rows, dtype=np.float64).reshape(-1, columns)


def valid_pose(pose: np.ndarray) -> np.ndarray | None:
    """The pose, or None if it has non-finite entries (ScanNet marks lost tracking with -inf)."""
    return pose if np.all(np.isfinite(pose)) else None
