"""Turn a wire frame message (the msgpack the phone sent) into an engine `Frame`, with clear errors.

Frames larger than the session's working resolution are brought down to it while decoding (a JPEG is decoded at
1/2, 1/4 or 1/8 scale by libjpeg itself), so a 8192x8192 frame never costs the worker per-pixel memory at its full
size; the intrinsics are scaled with the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from protocol.image_header import image_size
from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.geometry.lens import Lens, Undistortion, undistorted_camera, undistortion

DEFAULT_MAX_SIDE = 640  # the longest side a frame is worked on at (FLASHMONO_MAX_FRAME_SIDE)
_REDUCED_COLOR = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                  8: cv2.IMREAD_REDUCED_COLOR_8}


class FrameError(ValueError):
    """A frame that cannot be used; `code` is the error code sent back to the client."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def working_size(width: int, height: int, session_intrinsics: dict[str, Any] | None,
                 max_side: int = DEFAULT_MAX_SIDE) -> tuple[int, int]:
    """(width, height) a frame is worked on at: its own size, brought down (aspect kept) to the session's
    declared resolution and to `max_side`, whichever is smaller; never up."""
    longest = max(width, height)
    target = max_side
    if session_intrinsics:
        target = min(target, max(int(session_intrinsics["width"]), int(session_intrinsics["height"])))
    if longest <= target:
        return width, height
    scale = target / longest
    return max(1, round(width * scale)), max(1, round(height * scale))


def decode_frame(message: dict[str, Any], session_intrinsics: dict[str, Any] | None,
                 max_side: int = DEFAULT_MAX_SIDE, depth_in_colour: bool = True) -> Frame:
    """The Frame for a validated wire message {seq, timestamp, image, intrinsics?, depth?, pose?}, at the
    session's working resolution (see `working_size`), undistorted when its camera has a lens distortion (the
    depth too when it is registered to the colour image: `depth_in_colour`; a session's `depth_camera` depth is
    registered to the undistorted colour camera later)."""
    try:
        _, sent_w, sent_h = image_size(message["image"])
    except ValueError as err:
        raise FrameError("bad_image", f"image is not a valid JPEG/PNG: {err}") from err
    width, height = working_size(sent_w, sent_h, session_intrinsics, max_side)
    lens_fix = frame_undistortion(message.get("intrinsics"), session_intrinsics, sent_w, sent_h, width, height)
    image = _decode_image(message["image"], *(lens_fix.size if lens_fix is not None else (width, height)))
    intrinsics = frame_intrinsics(message.get("intrinsics"), session_intrinsics, sent_w, sent_h)
    if intrinsics is not None and (width, height) != (sent_w, sent_h):
        intrinsics = intrinsics.scaled(width, height)
    if lens_fix is not None:
        image, intrinsics = _resized(lens_fix.image(image), width, height, cv2.INTER_AREA), lens_fix.pinhole
    depth = None
    if message.get("depth") is not None:
        raw = cv2.imdecode(np.frombuffer(message["depth"], dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise FrameError("bad_depth", "depth must be a single-channel 16-bit PNG in millimetres")
        if raw.shape != (sent_h, sent_w):
            raise FrameError("bad_depth", f"depth is {raw.shape[1]}x{raw.shape[0]} but the image is "
                                          f"{sent_w}x{sent_h}")
        if lens_fix is not None and depth_in_colour:
            raw = lens_fix.depth(_resized(raw, *lens_fix.size, cv2.INTER_NEAREST))
        # nearest: averaging would mix valid depths with holes (0)
        depth = _resized(raw, width, height, cv2.INTER_NEAREST).astype(np.float32) / 1000.0
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


def _declared_camera(value: Any, session_intrinsics: dict[str, Any] | None, width: int, height: int
                     ) -> tuple[Intrinsics, dict[str, Any] | None] | None:
    """The camera the image was sent with, at the size it was declared at (the frame's own at the image's size,
    else the session's), and its wire distortion: the frame's own `distortion` when its intrinsics name one (null:
    none), else the session's (a lens does not change from frame to frame; its focal length may)."""
    session_lens = (session_intrinsics or {}).get("distortion")
    if isinstance(value, dict):
        camera = Intrinsics(*(float(value[k]) for k in ("fx", "fy", "cx", "cy")), width, height)
        return camera, value["distortion"] if "distortion" in value else session_lens
    if value is not None:
        return Intrinsics(*(float(v) for v in value), width, height), session_lens
    if session_intrinsics:
        return Intrinsics.from_dict(session_intrinsics), session_lens
    return None


@dataclass(frozen=True)
class FrameUndistortion:
    """How a frame with a lens is brought to its pinhole camera: decoded at `size`, undistorted there, then
    area-downscaled to the working size, whose camera is `pinhole`."""

    size: tuple[int, int]
    remap: Undistortion
    pinhole: Intrinsics

    def image(self, image: np.ndarray) -> np.ndarray:
        return self.remap.image(image)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        return self.remap.depth(depth)


def frame_undistortion(value: Any, session_intrinsics: dict[str, Any] | None, sent_w: int, sent_h: int,
                       width: int, height: int) -> FrameUndistortion | None:
    """The undistortion of a frame sent at sent_w x sent_h and worked on at width x height, None for a pinhole
    camera. It undistorts at up to twice the working size (as large as the frame is), so that its interpolation
    blurs only what the downscale to the working size takes away. The pinhole camera is computed where the camera
    was declared, then scaled, so that every frame and the session's own camera (`session_camera`) agree whatever
    the working size."""
    declared = _declared_camera(value, session_intrinsics, sent_w, sent_h)
    lens = Lens.from_wire(declared[1]) if declared is not None else None
    if lens is None:
        return None
    camera = declared[0]
    pinhole = undistorted_camera(camera, lens)
    size = (2 * width, 2 * height) if sent_w >= 2 * width and sent_h >= 2 * height else (sent_w, sent_h)
    remap = undistortion(camera.scaled(*size), lens, pinhole.scaled(*size))
    return FrameUndistortion(size, remap, pinhole.scaled(width, height))


def _resized(image: np.ndarray, width: int, height: int, interpolation: int) -> np.ndarray:
    return image if image.shape[:2] == (height, width) else cv2.resize(image, (width, height),
                                                                       interpolation=interpolation)


def session_camera(session_intrinsics: dict[str, Any] | None) -> Intrinsics | None:
    """The session's camera as the engine sees it: its pinhole camera after undistortion, if it has a lens
    distortion."""
    if not session_intrinsics:
        return None
    camera = Intrinsics.from_dict(session_intrinsics)
    lens = Lens.from_wire(session_intrinsics.get("distortion"))
    return camera if lens is None else undistorted_camera(camera, lens)


def _decode_image(data: bytes, width: int, height: int) -> np.ndarray:
    """RGB uint8 at width x height: decoded at the largest 1/2^k reduction still at least that big, then resized."""
    _, sent_w, sent_h = image_size(data)
    factor = max(f for f in _REDUCED_COLOR if -(-sent_w // f) >= width and -(-sent_h // f) >= height)
    bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), _REDUCED_COLOR[factor])
    if bgr is None:
        raise FrameError("bad_image", "image could not be decoded (corrupt or unsupported JPEG/PNG)")
    if not _complete_encoding(data):
        raise FrameError("bad_image", "image data is truncated")
    if bgr.shape[:2] != (height, width):
        bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _complete_encoding(data: bytes) -> bool:
    """JPEGs must end with EOI and PNGs with IEND: OpenCV decodes truncated files into partly grey images."""
    if data.startswith(b"\xff\xd8"):
        return data.rstrip(b"\x00").endswith(b"\xff\xd9")
    if data.startswith(b"\x89PNG"):
        return b"IEND" in data[-12:]
    return True
