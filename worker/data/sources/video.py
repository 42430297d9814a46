"""A video file decoded with OpenCV."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2

from worker.data.frame import Frame

from .base import DatasetError, FrameSource, SourceOptions, finish_frame

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")


class VideoSource(FrameSource):
    """Frames of a video file. Timestamps come from the container (CAP_PROP_POS_MSEC) when it reports them, else
    index / fps. The camera is unknown unless given with the `intrinsics` option (for the video's own size)."""

    def __init__(self, path: str | Path, options: SourceOptions) -> None:
        super().__init__(options)
        self.path = Path(path)
        if not self.path.is_file():
            raise DatasetError(f"video file not found: {self.path}")
        capture = cv2.VideoCapture(str(self.path))
        try:
            if not capture.isOpened():
                raise DatasetError(f"cannot open video {self.path} (corrupt or unsupported codec)")
            self.fps = capture.get(cv2.CAP_PROP_FPS) or 30.0
            self._frame_count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
            width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
            height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
            ok, _ = capture.read()
            if not ok:
                raise DatasetError(f"video {self.path} has no decodable frames")
        finally:
            capture.release()
        self.name = self.path.stem
        native = options.intrinsics
        if native is not None and (native.width, native.height) != (width, height):
            native = native.scaled(width, height)
        self._native_intrinsics = native
        size = options.resize or (width, height)
        self.intrinsics = None if native is None else native.scaled(*size)

    def __len__(self) -> int:
        if self._frame_count <= 0:
            raise TypeError(f"video {self.path} does not report its frame count")
        return len(self.options.selected(self._frame_count))

    def __iter__(self) -> Iterator[Frame]:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise DatasetError(f"cannot open video {self.path}")
        try:
            position, yielded = 0, 0
            while self.options.max_frames is None or yielded < self.options.max_frames:
                ok, bgr = capture.read()
                if not ok:
                    return
                if position % self.options.stride == 0:
                    msec = capture.get(cv2.CAP_PROP_POS_MSEC)
                    stamp = position / self.fps if msec <= 0 and position > 0 else msec / 1000.0
                    image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                    yield finish_frame(yielded, stamp, image, self._native_intrinsics, None, None, self.options)
                    yielded += 1
                position += 1
        finally:
            capture.release()
