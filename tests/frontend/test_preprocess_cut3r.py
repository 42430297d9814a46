"""Models converted from CUT3R get CUT3R's own resampling (PIL Lanczos when shrinking, bicubic when enlarging):
pixel-exact against PIL on real ICL images, where OpenCV's Lanczos-4 differs visibly."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from frontend_test_config import TEST_CONFIG, single_torch_thread  # noqa: F401
from PIL import Image

from worker.frontend import build_model
from worker.frontend.checkpoint import load_checkpoint, save_checkpoint
from worker.frontend.preprocess import centre_crop_box, prepare_image, resample_for, resized_size

ICL_IMAGE = Path(__file__).resolve().parents[1] / "data" / "icl_mini" / "rgb" / "00000.jpg"


@pytest.fixture(scope="module")
def icl_rgb() -> np.ndarray:
    return np.ascontiguousarray(cv2.imread(str(ICL_IMAGE))[..., ::-1])


@pytest.mark.parametrize("long_side,method", [(224, Image.Resampling.LANCZOS), (512, Image.Resampling.BICUBIC)])
def test_pil_resampling_is_pixel_exact_against_pil(icl_rgb, long_side, method) -> None:
    height, width = icl_rgb.shape[:2]
    size = resized_size(width, height, long_side)
    left, top, crop_w, crop_h = centre_crop_box(*size)
    expected = np.asarray(Image.fromarray(icl_rgb).resize(size, method))[top:top + crop_h, left:left + crop_w]
    prep = prepare_image(icl_rgb, long_side=long_side, resample="pil")
    ours = np.round(prep.tensor[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    assert np.array_equal(ours, expected)
    opencv = prepare_image(icl_rgb, long_side=long_side, resample="opencv")
    assert (opencv.tensor - prep.tensor).abs().max() * 255 >= 5  # the two resamplers really differ here


def test_resample_follows_the_checkpoint_source(tmp_path: Path) -> None:
    model = build_model(TEST_CONFIG)
    save_checkpoint(model, tmp_path / "converted.safetensors", {"source": "cut3r", "source_file": "x.pth"})
    save_checkpoint(model, tmp_path / "ours.safetensors", {"step": 10})
    assert resample_for(load_checkpoint(tmp_path / "converted.safetensors")) == "pil"
    assert resample_for(load_checkpoint(tmp_path / "ours.safetensors")) == "opencv"
    assert resample_for(torch.nn.Linear(1, 1)) == "opencv"


def test_unknown_resampler_is_refused(icl_rgb) -> None:
    with pytest.raises(ValueError, match="resample"):
        prepare_image(icl_rgb, long_side=224, resample="nearest")
