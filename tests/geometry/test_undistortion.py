"""Undistortion (worker.geometry.lens) on real images: an ICL frame seen through the TUM Kinect's lens and through
a fisheye comes back as the pinhole image of the same scene; depth keeps its own samples; the pinhole camera sees
only the photo; decode_frame undistorts a wire frame once, at the working size."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from lens_samples import FISHEYE, TUM_FR1, distort, to_pinhole

from worker.data import open_source
from worker.geometry import Intrinsics
from worker.geometry.lens import Lens, undistorted_camera, undistortion
from worker.runtime.frames import decode_frame, session_camera

ICL = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def frame():
    return next(iter(open_source(str(ICL), max_frames=1, use_gt_depth=True)))


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def _inner(image: np.ndarray, margin: int = 12) -> np.ndarray:
    return image[margin:-margin, margin:-margin]


@pytest.mark.parametrize("distortion", [TUM_FR1, FISHEYE], ids=["radtan", "fisheye"])
def test_a_distorted_real_image_comes_back_as_its_pinhole_image(frame, distortion) -> None:
    camera = frame.intrinsics
    seen = distort(frame.image, camera, distortion)
    lens = Lens.from_wire(distortion)
    pinhole = undistorted_camera(camera, lens)
    restored = undistortion(camera, lens, pinhole).image(seen)
    expected = to_pinhole(frame.image, camera, pinhole)
    assert _psnr(_inner(restored), _inner(expected)) > 30.0
    # the oracle can tell: the distorted image itself is far from the pinhole one
    assert _psnr(_inner(seen), _inner(expected)) < _psnr(_inner(restored), _inner(expected)) - 8.0


def test_the_pinhole_camera_sees_only_the_photo(frame) -> None:
    """alpha 0: every pixel of the undistorted image comes from inside the distorted photo."""
    camera, lens = frame.intrinsics, Lens.from_wire(TUM_FR1)
    pinhole = undistorted_camera(camera, lens)
    marker = np.full((camera.height, camera.width), 255, np.uint8)

    def outside(target: Intrinsics) -> float:
        maps = undistortion(camera, lens, target)._maps
        return float((cv2.remap(marker, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) == 0).mean())

    assert outside(pinhole) < 1e-3  # a corner pixel at most
    assert outside(camera) > 0.01  # the photo's own K would show what the lens did not see
    assert (pinhole.width, pinhole.height) == (camera.width, camera.height)


def test_depth_takes_its_nearest_sample_and_holes_stay_holes(frame) -> None:
    camera, lens = frame.intrinsics, Lens.from_wire(TUM_FR1)
    depth = np.round(frame.depth * 1000).astype(np.uint16)
    depth[100:140, 150:200] = 0  # a hole
    seen = distort(depth, camera, TUM_FR1, nearest=True)
    restored = undistortion(camera, lens, undistorted_camera(camera, lens)).depth(seen)
    assert restored.dtype == np.uint16
    assert set(np.unique(restored)) <= set(np.unique(seen)) | {0}  # no depth invented by averaging
    assert (restored == 0).mean() > 0.01  # the hole is still there


def test_a_lens_that_changes_nothing_is_no_lens() -> None:
    assert Lens.from_wire(None) is None
    assert Lens.from_wire({"model": "radtan", "k1": 0.0}) is None
    assert Lens.from_wire({"model": "fisheye", "k1": 0.01}) == Lens("fisheye", (0.01, 0.0, 0.0, 0.0))


def _wire(image: np.ndarray, seq: int, depth: np.ndarray | None = None, intrinsics=None) -> dict:
    message = {"seq": seq, "timestamp": seq / 30.0,
               "image": cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1].tobytes()}
    if depth is not None:
        message["depth"] = cv2.imencode(".png", depth)[1].tobytes()
    if intrinsics is not None:
        message["intrinsics"] = intrinsics
    return message


def test_decode_frame_undistorts_once_at_the_working_size(frame) -> None:
    """A 640x480 distorted frame worked on at 320x240: image and depth undistorted, its camera the session's
    pinhole camera at that size, whether the distortion comes with the session or with the frame."""
    big = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    image = cv2.resize(frame.image, (640, 480), interpolation=cv2.INTER_LINEAR)
    depth = cv2.resize(np.round(frame.depth * 1000).astype(np.uint16), (640, 480), interpolation=cv2.INTER_NEAREST)
    seen, seen_depth = distort(image, big, TUM_FR1), distort(depth, big, TUM_FR1, nearest=True)
    declared = {**big.to_dict(), "distortion": TUM_FR1}
    expected_camera = session_camera(declared).scaled(320, 240)
    expected = to_pinhole(frame.image, frame.intrinsics, expected_camera)

    by_session = decode_frame(_wire(seen, 0, seen_depth), declared, max_side=320)
    by_frame = decode_frame(_wire(seen, 1, seen_depth, intrinsics={**big.to_dict(), "distortion": TUM_FR1}),
                            None, max_side=320)
    pinhole_only = decode_frame(_wire(seen, 2, seen_depth), big.to_dict(), max_side=320)
    for decoded in (by_session, by_frame):
        assert decoded.image.shape == (240, 320, 3)
        assert decoded.intrinsics == expected_camera
        assert _psnr(_inner(decoded.image), _inner(expected)) > 35.0
        assert np.count_nonzero(decoded.depth) > 0.9 * np.count_nonzero(frame.depth)
    assert _psnr(_inner(pinhole_only.image), _inner(expected)) < 30.0  # the session that did not say so
    kept = decode_frame(_wire(seen, 3, seen_depth), declared, max_side=320, depth_in_colour=False)
    unmoved = cv2.resize(seen_depth, (320, 240), interpolation=cv2.INTER_NEAREST).astype(np.float32) / 1000.0
    assert np.array_equal(kept.depth, unmoved)


def test_a_frames_own_focal_length_keeps_the_sessions_lens_unless_it_names_one(frame) -> None:
    """A lens does not change from frame to frame, its focal length may (autofocus): a frame's intrinsics without
    `distortion` are undistorted with the session's lens; `distortion: null` says the frame has none."""
    camera = frame.intrinsics
    seen = distort(frame.image, camera, TUM_FR1)
    declared = {**camera.to_dict(), "distortion": TUM_FR1}
    own_k = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
    kept = decode_frame(_wire(seen, 0, intrinsics=own_k), declared)
    as_list = decode_frame(_wire(seen, 1, intrinsics=list(own_k.values())), declared)
    none = decode_frame(_wire(seen, 2, intrinsics={**own_k, "distortion": None}), declared)
    pinhole = session_camera(declared)
    assert kept.intrinsics == as_list.intrinsics == pinhole and none.intrinsics == camera
    assert np.array_equal(kept.image, as_list.image) and np.array_equal(none.image, seen)
