"""Image preparation as CUT3R does it: resize the long side, centre-crop both sides to multiples of 16.

Weights converted from CUT3R saw images resized by PIL (Lanczos / bicubic); OpenCV's Lanczos-4 differs from it by up
to 30 grey levels, so such models get PIL's resampling (`resample_for(model)` says which one a model wants).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
import torch

from worker.geometry import Intrinsics

Resample = Literal["opencv", "pil"]


@dataclass(frozen=True)
class PreparedImage:
    """The model input and how it relates to the original image.

    tensor: [1, 3, h, w] float in [0, 1]. intrinsics: adjusted to the prepared image, or None when unknown.
    scale: resized width / original width. crop: (left, top, width, height) of the crop in the resized image.
    """

    tensor: torch.Tensor
    intrinsics: Intrinsics | None
    scale: float
    crop: tuple[int, int, int, int]


def resized_size(width: int, height: int, long_side: int) -> tuple[int, int]:
    """(width, height) after scaling the longer side to `long_side` (rounded to the nearest pixel)."""
    longest = max(width, height)
    return int(round(width * long_side / longest)), int(round(height * long_side / longest))


def centre_crop_box(width: int, height: int, patch: int = 16) -> tuple[int, int, int, int]:
    """(left, top, width, height) of CUT3R's centre crop: each side down to a multiple of `patch` around
    (W//2, H//2); a square image is cropped to a 4:3 landscape window."""
    cx, cy = width // 2, height // 2
    half_w = ((2 * cx) // patch) * (patch // 2)
    half_h = ((2 * cy) // patch) * (patch // 2)
    if width == height:
        half_h = (3 * half_w) // 4
        half_h -= half_h % (patch // 2)
    if half_w == 0 or half_h == 0:
        raise ValueError(f"image {width}x{height} is too small to crop to multiples of {patch}")
    return cx - half_w, cy - half_h, 2 * half_w, 2 * half_h


def resample_for(model: Any) -> Resample:
    """"pil" for a model converted from CUT3R weights (its checkpoint metadata says source "cut3r"), else "opencv"."""
    metadata = getattr(model, "checkpoint_metadata", None) or {}
    return "pil" if metadata.get("source") == "cut3r" else "opencv"


def resize_rgb(rgb: np.ndarray, size: tuple[int, int], resample: Resample = "opencv") -> np.ndarray:
    """`rgb` resized to `size` (width, height): Lanczos when shrinking, bicubic when enlarging, by OpenCV or PIL."""
    shrink = size[0] < rgb.shape[1] or size[1] < rgb.shape[0]
    if resample == "pil":
        from PIL import Image

        method = Image.Resampling.LANCZOS if shrink else Image.Resampling.BICUBIC
        return np.array(Image.fromarray(rgb).resize(size, method))
    if resample != "opencv":
        raise ValueError(f"resample must be 'opencv' or 'pil', got {resample!r}")
    return cv2.resize(rgb, size, interpolation=cv2.INTER_LANCZOS4 if shrink else cv2.INTER_CUBIC)


def prepare_image(rgb: np.ndarray, intrinsics: Intrinsics | None = None, long_side: int = 512,
                  patch: int = 16, resample: Resample = "opencv") -> PreparedImage:
    """Resize an RGB uint8 image [H, W, 3] so its long side is `long_side` (Lanczos when shrinking, bicubic when
    enlarging; `resample` "pil" as CUT3R does), centre-crop it to multiples of `patch`, and adjust the intrinsics
    when given."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 image [H, W, 3], got {rgb.dtype} {rgb.shape}")
    if long_side < patch or long_side % patch:
        raise ValueError(f"long_side must be a positive multiple of {patch}, got {long_side}")
    height, width = rgb.shape[:2]
    if intrinsics is not None and (intrinsics.width, intrinsics.height) != (width, height):
        raise ValueError(
            f"intrinsics are for {intrinsics.width}x{intrinsics.height} but the image is {width}x{height}")
    new_w, new_h = resized_size(width, height, long_side)
    if (new_w, new_h) != (width, height):
        rgb = resize_rgb(np.ascontiguousarray(rgb), (new_w, new_h), resample)
    left, top, crop_w, crop_h = centre_crop_box(new_w, new_h, patch)
    rgb = rgb[top:top + crop_h, left:left + crop_w]
    tensor = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float() / 255.0
    adjusted = None
    if intrinsics is not None:
        adjusted = intrinsics.scaled(new_w, new_h).cropped(left, top, crop_w, crop_h)
    return PreparedImage(tensor, adjusted, new_w / width, (left, top, crop_w, crop_h))
