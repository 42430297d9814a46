"""Visual odometry's camera: the session's image size held to, and for an uncalibrated camera the focal length
measured from the frames before the first map (`self_calibration.FocalEstimator`), frozen once the map is made."""

from __future__ import annotations

import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics

from .vo_state import VoState


def camera_of(s: VoState, frame: Frame, intrinsics: Intrinsics | None) -> Intrinsics:
    """The frame's camera: the given intrinsics (else the frame's), else the focal estimate; raises ValueError
    where the frame's size is not the session's or not the intrinsics'."""
    size = (frame.width, frame.height)
    if s.image_size is not None and size != s.image_size:
        raise ValueError(f"frame {frame.index} is {size[0]}x{size[1]} but this session's frames are "
                         f"{s.image_size[0]}x{s.image_size[1]}")
    intrinsics = intrinsics or frame.intrinsics
    if intrinsics is not None and (intrinsics.width, intrinsics.height) != size:
        raise ValueError(f"intrinsics are for {intrinsics.width}x{intrinsics.height} but frame {frame.index} "
                         f"is {size[0]}x{size[1]}")
    s.image_size = size
    if intrinsics is not None:
        return intrinsics
    s.estimated_intrinsics = s.focal.intrinsics(*size)
    return s.estimated_intrinsics


def measure_focal(s: VoState, uv_a: np.ndarray, uv_b: np.ndarray, camera: Intrinsics) -> Intrinsics:
    """The camera with the focal estimate after the matches uv_a, uv_b [n, 2] of two waiting frames (the same
    camera once the estimate is frozen)."""
    if s.focal.frozen:
        return camera
    s.focal.observe_matches(uv_a, uv_b, camera)
    s.estimated_intrinsics = s.focal.intrinsics(camera.width, camera.height)
    return s.estimated_intrinsics


def freeze_focal(s: VoState) -> None:
    """The first map is made on the current estimate: it holds from now on."""
    s.focal.freeze()
