"""Turn a wire frame message (the msgpack the phone sent) into an engine `Frame`, with clear errors."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics


class FrameError(ValueError):
    """A frame that cannot be used; `code` is the error code sent back to the client."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def decode_frame(message: dict[str, Any], session_intrinsics: dict[str, Any] | None) -> Frame:
    """The Frame for a validated wire message {seq, timestamp, image, intrinsics?, depth?, pose?}."""
    image = _decode_image(message["image"])
    height, width = image.shape[:2]
    intrinsics = frame_intrinsics(message.get("intrinsics"), session_intrinsics, width, height)
    depth = None
    if message.get("depth") is not None:
        raw = cv2.imdecode(np.frombuffer(message["depth"], dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise FrameError("bad_depth", "depth must be a single-channel 16-bit PNG in millimetres")
        if raw.shape != (height, width):
            raise FrameError("bad_depth", f"depth is {raw.shape[1]}x{raw.shape[0]} but the image is {width}x{height}")
        depth = raw.astype(np.float32) / 1000.0
    pose = None
    if message.get("pose") is not None:
        pose = np.asarray(message["pose"], dtype=np.float64).reshape(4, 4)
    return Frame(index=int(message["seq"]), timestamp=float(message["timestamp"]), image=image,
                 intrinsics=intrinsics, depth=depth, pose=pose)


def frame_intrinsics(value: Any, session_intrinsics: dict[str, Any] | None, width: int, height: int
                     ) -> Intrinsics | None:
    """The frame's camera: its own fx,fy,cx,cy if sent, else the session's (rescaled to the image size)."""
    if value is not None:
        if isinstance(value, dict):
            fx, fy, cx, cy = (float(value[k]) for k in ("fx", "fy", "cx", "cy"))
        else:
            fx, fy, cx, cy = (float(v) for v in value)
        return Intrinsics(fx, fy, cx, cy, width, height)
    if session_intrinsics:
        base = Intrinsics.from_dict(session_intrinsics)
        return base if (base.width, base.height) == (width, height) else base.scaled(width, height)
    return None


def _decode_image(data: bytes) -> np.ndarray:
    buf = np.frombuffer(data, dtype=np.uint8)
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if bgr is None:
        raise FrameError("bad_image", "image could not be decoded (corrupt or unsupported JPEG/PNG)")
    if not _complete_encoding(data):
        raise FrameError("bad_image", "image data is truncated")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _complete_encoding(data: bytes) -> bool:
    """JPEGs must end with EOI and PNGs with IEND: OpenCV decodes truncated files into partly grey images."""
    if data.startswith(b"\xff\xd8"):
        return data.rstrip(b"\x00").endswith(b"\xff\xd9")
    if data.startswith(b"\x89PNG"):
        return b"IEND" in data[-12:]
    return True
