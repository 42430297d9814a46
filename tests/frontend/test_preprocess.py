"""Image preparation: CUT3R's resize + centre crop, intrinsics bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from worker.frontend.preprocess import centre_crop_box, prepare_image, resized_size
from worker.geometry import Intrinsics


def _gradient(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x % 256, y % 256, (x + y) % 256], axis=-1).astype(np.uint8)


def test_640x480_becomes_512x384_with_scaled_intrinsics() -> None:
    K = Intrinsics(481.2, 480.0, 319.5, 239.5, 640, 480)
    prep = prepare_image(_gradient(480, 640), K, long_side=512)
    assert prep.tensor.shape == (1, 3, 384, 512)
    assert prep.crop == (0, 0, 512, 384) and prep.scale == pytest.approx(0.8)
    assert prep.intrinsics == Intrinsics(481.2 * 0.8, 384.0, 319.5 * 0.8, 239.5 * 0.8, 512, 384)
    assert 0.0 <= float(prep.tensor.min()) and float(prep.tensor.max()) <= 1.0


def test_224_long_side_crops_height_to_a_multiple_of_16() -> None:
    K = Intrinsics(481.2, 480.0, 319.5, 239.5, 640, 480)
    prep = prepare_image(_gradient(480, 640), K, long_side=224)
    assert prep.tensor.shape == (1, 3, 160, 224)
    assert prep.crop == (0, 4, 224, 160)
    s = 224 / 640
    assert prep.intrinsics.fx == pytest.approx(481.2 * s) and prep.intrinsics.fy == pytest.approx(480.0 * 168 / 480)
    assert prep.intrinsics.cx == pytest.approx(319.5 * s) and prep.intrinsics.cy == pytest.approx(239.5 * s - 4)


def test_kitti_size_and_square_and_portrait() -> None:
    assert resized_size(1242, 375, 512) == (512, 155)
    assert prepare_image(_gradient(375, 1242)).tensor.shape == (1, 3, 144, 512)
    square = prepare_image(_gradient(512, 512))
    assert square.tensor.shape == (1, 3, 384, 512) and square.crop == (0, 64, 512, 384)
    portrait = prepare_image(_gradient(640, 480))
    assert portrait.tensor.shape == (1, 3, 512, 384) and portrait.intrinsics is None


def test_crop_is_centred() -> None:
    assert centre_crop_box(512, 155) == (0, 5, 512, 144)
    assert centre_crop_box(500, 300) == (2, 6, 496, 288)


def test_pixels_match_a_pil_lanczos_resize_closely() -> None:
    rgb = _gradient(480, 640)
    prep = prepare_image(rgb, long_side=512)
    ref = np.asarray(Image.fromarray(rgb).resize((512, 384), Image.LANCZOS)).astype(np.float32) / 255
    ours = prep.tensor[0].permute(1, 2, 0).numpy()
    assert np.median(np.abs(ours - ref)) < 0.02


def test_identity_when_already_the_right_size() -> None:
    rgb = _gradient(384, 512)
    prep = prepare_image(rgb)
    assert np.array_equal((prep.tensor[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), rgb)


def test_bad_inputs_are_rejected() -> None:
    with pytest.raises(ValueError, match="uint8"):
        prepare_image(np.zeros((480, 640, 3), np.float32))
    with pytest.raises(ValueError, match="RGB"):
        prepare_image(np.zeros((480, 640), np.uint8))
    with pytest.raises(ValueError, match="multiple of 16"):
        prepare_image(np.zeros((480, 640, 3), np.uint8), long_side=500)
    with pytest.raises(ValueError, match="intrinsics are for"):
        prepare_image(np.zeros((480, 640, 3), np.uint8), Intrinsics(500, 500, 320, 240, 320, 240))
    with pytest.raises(ValueError, match="too small"):
        prepare_image(np.zeros((4, 640, 3), np.uint8))
