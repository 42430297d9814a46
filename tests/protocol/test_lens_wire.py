"""The wire form of a lens distortion (protocol.lens): real calibrations pass, coefficients that fold the image
or do not belong to the model are refused with the reason."""

from __future__ import annotations

import math

import pytest

from protocol.lens import coefficients, distortion_problem, is_identity

TUM_640 = (517.306408, 516.469215, 318.643040, 255.313989, 640, 480)
FOX = (1375.52, 1374.49, 554.558, 965.268, 1080, 1920)  # instant-ngp's fox, a phone's portrait photos (COLMAP)


@pytest.mark.parametrize("distortion, camera", [
    ({"model": "radtan", "k1": 0.262383, "k2": -0.953104, "p1": -0.005358, "p2": 0.002628, "k3": 1.163314}, TUM_640),
    ({"k1": 0.0578421, "k2": -0.0805099, "p1": -0.000980296, "p2": 0.00015575}, FOX),
    ({"model": "fisheye", "k1": -0.013, "k2": 0.021, "k3": -0.011, "k4": 0.002}, (300.0, 300.0, 320.0, 240.0, 640,
                                                                                  480)),
    ({"model": "radtan"}, TUM_640),
])
def test_real_calibrations_pass(distortion, camera) -> None:
    assert distortion_problem(distortion, *camera) is None


@pytest.mark.parametrize("distortion, reason", [
    ({"k1": -0.9}, "folds"),  # barrel so strong the radius turns back before the corners
    ({"k1": 1.0, "k2": -2.0}, "folds"),
    ({"model": "fisheye", "p1": 0.01}, "unknown: p1"),
    ({"model": "radtan", "k4": 0.01}, "unknown: k4"),
    ({"model": "division", "k1": 0.1}, "model must be one of"),
    ({"k1": math.nan}, "finite"),
    ({"k1": True}, "finite"),
    ({"k1": 5e3}, "out of range"),
    ([0.1, 0.0, 0.0, 0.0], "object"),
])
def test_bad_distortions_are_refused_with_the_reason(distortion, reason) -> None:
    problem = distortion_problem(distortion, *TUM_640)
    assert problem is not None and reason in problem, problem


def test_coefficients_come_in_opencvs_order_with_zeros_for_the_missing() -> None:
    assert coefficients({"k3": 3.0, "p2": 2.0, "k1": 1.0}) == ("radtan", (1.0, 0.0, 0.0, 2.0, 3.0))
    assert coefficients({"model": "fisheye", "k4": 4.0, "k1": 1.0}) == ("fisheye", (1.0, 0.0, 0.0, 4.0))
    assert is_identity(None) and is_identity({"model": "fisheye", "k2": 0.0})
    assert not is_identity({"p1": 1e-4})
