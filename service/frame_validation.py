"""Gateway-side checks of a streamed frame message, cheap enough for every frame (no pixel decoding).

The worker decodes the pixels and reports images that turn out corrupt past their header.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from protocol.codec import unpack
from protocol.image_header import PNG_SIGNATURE, image_size
from protocol.lens import distortion_problem
from protocol.limits import MAX_IMAGE_SIDE, MAX_SEQ
from service.pose_check import pose_problem


class FrameRejected(ValueError):
    """A frame refused with an error `code` ("bad_message", "bad_image", "bad_intrinsics", ...)."""

    def __init__(self, code: str, message: str, seq: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.seq = seq


@dataclass(frozen=True)
class CheckedFrame:
    seq: int
    width: int
    height: int


def check_frame_message(data: bytes, max_bytes: int, session_intrinsics: dict[str, Any] | None) -> CheckedFrame:
    """Validate a binary frame message; raise FrameRejected with a clear message."""
    if len(data) > max_bytes:
        raise FrameRejected("too_large", f"frame message of {len(data)} bytes exceeds the limit of {max_bytes}")
    try:
        message = unpack(data)
    except ValueError as err:
        raise FrameRejected("bad_message", f"binary messages must be msgpack maps: {err}") from err
    if not isinstance(message, dict) or message.get("type") != "frame":
        raise FrameRejected("bad_message", 'binary messages must be msgpack maps with type "frame"')
    seq = message.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0 or seq >= MAX_SEQ:
        raise FrameRejected("bad_message", "seq must be a non-negative integer")
    timestamp = message.get("timestamp")
    if not isinstance(timestamp, (int, float)) or isinstance(timestamp, bool) or not math.isfinite(timestamp):
        raise FrameRejected("bad_message", "timestamp must be a finite number", seq)
    image = message.get("image")
    if not isinstance(image, bytes) or not image:
        raise FrameRejected("bad_image", "image must be JPEG or PNG bytes", seq)
    try:
        _, width, height = image_size(image)
    except ValueError as err:
        raise FrameRejected("bad_image", f"image is not a valid JPEG/PNG: {err}", seq) from err
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise FrameRejected("bad_image", f"image of {width}x{height} exceeds {MAX_IMAGE_SIDE} pixels a side", seq)
    _check_intrinsics(message.get("intrinsics"), session_intrinsics, width, height, seq)
    depth = message.get("depth")
    if depth is not None:
        if not isinstance(depth, bytes) or not depth.startswith(PNG_SIGNATURE):
            raise FrameRejected("bad_depth", "depth must be a 16-bit PNG in millimetres", seq)
        try:
            _, dw, dh = image_size(depth)
        except ValueError as err:
            raise FrameRejected("bad_depth", f"depth PNG is invalid: {err}", seq) from err
        if (dw, dh) != (width, height):
            raise FrameRejected("bad_depth", f"depth is {dw}x{dh} but the image is {width}x{height}", seq)
    pose = message.get("pose")
    if pose is not None:
        if not isinstance(pose, list):
            raise FrameRejected("bad_pose", "pose must be 16 finite floats (camera-to-world, row-major)", seq)
        problem = pose_problem(pose)
        if problem:
            raise FrameRejected("bad_pose", problem, seq)
    return CheckedFrame(seq=seq, width=width, height=height)


def _check_intrinsics(value: Any, session_intrinsics: dict[str, Any] | None, width: int, height: int,
                      seq: int) -> None:
    if value is None:
        if session_intrinsics:
            sw, sh = session_intrinsics["width"], session_intrinsics["height"]
            if abs(sw / sh - width / height) > 0.01 * (sw / sh):
                raise FrameRejected("bad_intrinsics", f"image is {width}x{height} but the session's intrinsics "
                                    f"are for {sw}x{sh} (another aspect ratio); send per-frame intrinsics", seq)
        return
    if isinstance(value, dict):
        try:
            values = [value[k] for k in ("fx", "fy", "cx", "cy")]
        except KeyError as err:
            raise FrameRejected("bad_intrinsics", f"intrinsics lack {err.args[0]}", seq) from err
    elif isinstance(value, list) and len(value) == 4:
        values = value
    else:
        raise FrameRejected("bad_intrinsics", "intrinsics must be {fx, fy, cx, cy} or [fx, fy, cx, cy]", seq)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
        raise FrameRejected("bad_intrinsics", "intrinsics must be finite numbers", seq)
    fx, fy, cx, cy = values
    if fx <= 0 or fy <= 0:
        raise FrameRejected("bad_intrinsics", f"focal lengths must be positive, got fx={fx}, fy={fy}", seq)
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise FrameRejected("bad_intrinsics",
                            f"principal point ({cx}, {cy}) lies outside the {width}x{height} image", seq)
    distortion = value.get("distortion") if isinstance(value, dict) else None
    if distortion is not None:
        problem = distortion_problem(distortion, fx, fy, cx, cy, width, height)
        if problem:
            raise FrameRejected("bad_intrinsics", problem, seq)
