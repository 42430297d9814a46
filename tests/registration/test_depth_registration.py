"""RGB-D registration: a misregistered synthetic RGB-D pair (depth camera 5 cm beside the colour one, its own
intrinsics) is registered with the given extrinsic, and detected without it, in the engine too; bad extrinsics are
refused."""

from __future__ import annotations

import numpy as np
import pytest
from registration_scene import render, rig

from worker.config import SlamConfig
from worker.data.frame import Frame
from worker.data.registration import MisregistrationDetector, register_depth
from worker.data.registration_config import DepthCameraConfig
from worker.slam import SlamSystem


@pytest.fixture(scope="module")
def pair():
    colour, depth_camera, depth_to_colour = rig()
    image, true_depth = render(colour, np.eye(4))
    _, raw_depth = render(depth_camera, depth_to_colour)
    return colour, depth_camera, depth_to_colour, image, true_depth, raw_depth


def _wrong(depth: np.ndarray, truth: np.ndarray) -> float:
    """Share of pixels with depth that are more than 5 cm off."""
    valid = depth > 0
    return float(np.mean(np.abs(depth[valid] - truth[valid]) > 0.05))


def test_depth_is_registered_to_the_colour_camera(pair) -> None:
    colour, depth_camera, depth_to_colour, _, true_depth, raw_depth = pair
    assert _wrong(raw_depth, true_depth) > 0.1  # as the sensor sends it, a fifth of the pixels are off
    registered = register_depth(raw_depth, depth_camera, colour, depth_to_colour)
    assert registered.shape == true_depth.shape and registered.dtype == np.float32
    assert np.mean(registered > 0) > 0.75  # holes: the depth camera's narrower view, occlusion shadows
    assert _wrong(registered, true_depth) < 0.01
    valid = registered > 0
    assert np.median(np.abs(registered[valid] - true_depth[valid])) < 1e-3


def test_misregistration_is_detected_and_registered_depth_passes(pair) -> None:
    colour, depth_camera, depth_to_colour, image, true_depth, raw_depth = pair
    verdicts = {}
    for name, depth in (("raw", raw_depth), ("registered", register_depth(raw_depth, depth_camera, colour,
                                                                          depth_to_colour)), ("true", true_depth)):
        detector = MisregistrationDetector(frames=1, max_shift=8)
        detector.add(image, depth)
        verdicts[name] = detector.verdict()
    assert verdicts["raw"].misregistered and verdicts["raw"].shift != (0, 0)
    assert not verdicts["registered"].misregistered and verdicts["registered"].shift == (0, 0)
    assert not verdicts["true"].misregistered


def _frames(pair, n: int = 6, registered_depth: bool = False) -> list[Frame]:
    colour, depth_camera, depth_to_colour, _, _, _ = pair
    frames = []
    for k in range(n):  # the rig slides sideways 1 cm per frame
        pose = np.eye(4)
        pose[0, 3] = 0.01 * k
        image, true_depth = render(colour, pose)
        _, raw = render(depth_camera, pose @ depth_to_colour)
        frames.append(Frame(k, k / 30, image, intrinsics=colour, depth=true_depth if registered_depth else raw,
                            pose=pose))
    return frames


def _engine(depth_camera: dict | None) -> SlamSystem:
    return SlamSystem(SlamConfig.preset("test", mapping={"enabled": False}, loop={"enabled": False},
                                        input={"pose_mode": "fixed", "surfel_init": "depth",
                                               "depth_camera": depth_camera}))


def _events(frames: list[Frame], depth_camera: dict | None = None) -> list[dict]:
    system = _engine(depth_camera)
    return [e for frame in frames for e in system.push(frame).events]


def test_the_engine_reports_misregistered_depth_once(pair) -> None:
    events = _events(_frames(pair))
    assert [e.TYPE for e in events] == ["depth_misregistered"]
    assert events[0].shift_px != [0, 0] and "depth_camera" in events[0].message
    assert _events(_frames(pair, registered_depth=True)) == []


def test_the_engine_maps_registered_depth_with_the_given_depth_camera(pair) -> None:
    colour, depth_camera, depth_to_colour, _, true_depth, _ = pair
    given = {**depth_camera.to_dict(), "depth_to_color": depth_to_colour.tolist()}
    wrong = {}
    for name, declared in (("declared", given), ("not declared", None)):
        system = SlamSystem(SlamConfig.preset(
            "test", loop={"enabled": False}, mapping={"refine_iterations": 1, "final_refine_passes": 0},
            input={"pose_mode": "fixed", "surfel_init": "depth", "depth_camera": declared}))
        events = [e for frame in _frames(pair, n=2) for e in system.push(frame).events]
        system.finish()
        _, rendered = system.render_view(np.eye(4), colour.matrix().numpy(), colour.width, colour.height)
        wrong[name] = _wrong(rendered, true_depth)
        assert not any(e.TYPE == "depth_misregistered" for e in events) or declared is None
        system.close()
    # (rendered surfels blend across depth edges, so neither is 0; misregistered depth puts a third more pixels off)
    assert wrong["declared"] < 0.8 * wrong["not declared"], wrong


@pytest.mark.parametrize("matrix, message", [
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "4x4"),
    ([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "not a rotation"),
    ([[1, 0, 0, 52.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "metres"),
    ([[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "finite"),
])
def test_bad_extrinsics_are_refused(matrix, message) -> None:
    with pytest.raises(ValueError, match=message):
        DepthCameraConfig(fx=200, fy=200, cx=80, cy=60, width=160, height=120, depth_to_color=matrix)
