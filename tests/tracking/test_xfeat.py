"""The vendored XFeat network (weights from safetensors) on a real ICL frame and a warped copy of it with a known
homography: keypoints and unit descriptors, matches that follow the warp, descriptors sampled at given pixels that
agree with the detector's."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from worker.data import open_source
from worker.tracking.xfeat import XFeatExtractor, mutual_matches

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def gray() -> np.ndarray:
    frame = next(iter(open_source(DATA, use_gt_depth=False, use_gt_poses=False)))
    return cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)


@pytest.fixture(scope="module")
def xfeat() -> XFeatExtractor:
    return XFeatExtractor(top_k=512)


def test_matches_follow_a_known_warp(gray, xfeat):
    # A turn and zoom as a homography (OpenCV pixel convention: centres at integers).
    H = np.array([[1.05, 0.04, -12.0], [-0.03, 1.02, 6.0], [1e-4, 0.0, 1.0]])
    warped = cv2.warpPerspective(gray, H, (gray.shape[1], gray.shape[0]), flags=cv2.INTER_LINEAR)
    a, b = xfeat.extract(gray), xfeat.extract(warped)
    assert 100 <= len(a) <= 512 and a.keypoints.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(a.descriptors, axis=1), 1.0, atol=1e-4)
    ia, ib = mutual_matches(a.descriptors, b.descriptors)
    assert len(ia) >= 80
    expected = cv2.perspectiveTransform((a.keypoints[ia] - 0.5)[None].astype(np.float64), H)[0] + 0.5
    error = np.linalg.norm(expected - b.keypoints[ib], axis=1)
    assert np.mean(error < 3.0) > 0.75  # XFeat keypoints sit on whole pixels; 80 % here


def test_descriptors_at_given_pixels_agree_with_the_detector(gray, xfeat):
    found = xfeat.extract(gray)
    again = xfeat.describe(gray, found.keypoints[:50])
    np.testing.assert_allclose(again, found.descriptors[:50], atol=1e-4)


def test_bad_images_are_refused(xfeat):
    with pytest.raises(ValueError):
        xfeat.extract(np.zeros((16, 16), np.uint8))
    with pytest.raises(ValueError):
        xfeat.extract(np.zeros((64, 64, 3), np.uint8))
