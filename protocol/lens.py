"""Lens distortion as a camera's intrinsics carry it on the wire, and the checks it must pass.

Two of OpenCV's models, with their coefficients named (the order of a coefficient list differs between OpenCV,
Android's LENS_DISTORTION and COLMAP, so the wire names each one):
- `radtan`: radial-tangential (Brown-Conrady), `k1 k2 p1 p2 [k3]`; phones, webcams, COLMAP's OPENCV camera;
- `fisheye`: equidistant (Kannala-Brandt), `k1 k2 k3 k4`; wide-angle and fisheye lenses, COLMAP's OPENCV_FISHEYE.
Coefficients not given are 0. The worker undistorts every frame once, before tracking, to a pinhole camera of the
same size whose pixels all lie inside the photo (the session's `estimated_intrinsics`).

A distortion is refused when its mapping is not one to one over the image (the radius folds back before the image's
corners), the sign of coefficients given in another convention or units. Pure Python: the gateway checks it too.
"""

from __future__ import annotations

import math
from typing import Any

RADTAN = "radtan"
FISHEYE = "fisheye"
MODEL_KEYS: dict[str, tuple[str, ...]] = {RADTAN: ("k1", "k2", "p1", "p2", "k3"), FISHEYE: ("k1", "k2", "k3", "k4")}
MAX_ABS_COEFFICIENT = 1e3
_STEPS = 2000  # samples of the radius when checking that the mapping does not fold
_MAX_RADTAN_RADIUS = math.tan(math.radians(85.0))  # a pinhole lens with radial distortion sees less than 170 degrees
_MAX_FISHEYE_ANGLE = math.radians(89.0)  # undistorted to a pinhole: rays at 90 degrees or more have no image


def coefficients(distortion: dict[str, Any]) -> tuple[str, tuple[float, ...]]:
    """(model, coefficients in OpenCV's order) of a checked wire distortion: radtan (k1, k2, p1, p2, k3), fisheye
    (k1, k2, k3, k4); missing ones are 0."""
    model = str(distortion.get("model", RADTAN))
    return model, tuple(float(distortion.get(key) or 0.0) for key in MODEL_KEYS[model])


def is_identity(distortion: dict[str, Any] | None) -> bool:
    """Whether a (checked) wire distortion changes nothing: absent, or every coefficient 0."""
    return distortion is None or not any(coefficients(distortion)[1])


def distortion_problem(distortion: Any, fx: float, fy: float, cx: float, cy: float, width: float,
                       height: float) -> str | None:
    """Why `distortion` is not a usable lens model for this camera; None when it is one."""
    if not isinstance(distortion, dict):
        return "distortion must be an object {model, k1, k2, ...}"
    model = distortion.get("model", RADTAN)
    if model not in MODEL_KEYS:
        return f"distortion model must be one of {', '.join(MODEL_KEYS)}, got {model!r}"
    allowed = set(MODEL_KEYS[model]) | {"model"}
    unknown = sorted(key for key, value in distortion.items() if key not in allowed and value is not None)
    if unknown:
        return (f"distortion model {model} takes {', '.join(MODEL_KEYS[model])}; unknown: {', '.join(unknown)}")
    for key in MODEL_KEYS[model]:
        value = distortion.get(key)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return f"distortion {key} must be a finite number"
        if abs(value) > MAX_ABS_COEFFICIENT:
            return f"distortion {key} = {value:g} is out of range (|k| <= {MAX_ABS_COEFFICIENT:g})"
    corner = _corner_radius(fx, fy, cx, cy, width, height)
    _, k = coefficients(distortion)
    if model == RADTAN:
        return _radial_problem(lambda r: r * (1 + k[0] * r**2 + k[1] * r**4 + k[4] * r**6), corner,
                               _MAX_RADTAN_RADIUS, "radius")
    return _radial_problem(lambda t: t * (1 + k[0] * t**2 + k[1] * t**4 + k[2] * t**6 + k[3] * t**8), corner,
                           _MAX_FISHEYE_ANGLE, "angle", reaches_required=False)


def _corner_radius(fx: float, fy: float, cx: float, cy: float, width: float, height: float) -> float:
    """The largest normalised distance from the principal point to an image corner (distorted coordinates)."""
    return max(math.hypot((x - cx) / fx, (y - cy) / fy) for x in (0.0, width) for y in (0.0, height))


def _radial_problem(distorted, corner: float, limit: float, what: str, reaches_required: bool = True) -> str | None:
    """Whether the radial mapping `distorted` rises steadily from 0 until it reaches the image corners' radius
    `corner` (searched up to the undistorted `limit`); a fisheye need not reach it (its corners may see past 90
    degrees, which the pinhole it is undistorted to crops away)."""
    previous = 0.0
    for step in range(1, _STEPS + 1):
        value = distorted(limit * step / _STEPS)
        if value <= previous:
            return (f"the distortion folds the image over itself: its distorted {what} stops growing at "
                    f"{previous:.3g} before the image's corners ({corner:.3g}, normalised); check the coefficients' "
                    "model, order and signs")
        if value >= corner:
            return None
        previous = value
    if reaches_required:
        return (f"the distortion maps the image's corners ({corner:.3g}, normalised) beyond a field of view of "
                "170 degrees; check the coefficients' model, order and signs")
    return None
