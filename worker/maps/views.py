"""A map package's keyframes as the localizer sees them: grey image, depth in the keyframe's units, pose and camera."""

from __future__ import annotations

import cv2
import numpy as np

from protocol.map_package import MapKeyframe, MapPackage

from .localizer import MapView


def view_of_keyframe(keyframe: MapKeyframe) -> MapView:
    """One keyframe as a `MapView` (its depth stays at the package's half resolution: the localizer reads it at
    its keypoints and brings it to the image's size where it aligns)."""
    grey = cv2.imdecode(np.frombuffer(keyframe.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise ValueError(f"keyframe {keyframe.id}: the image does not decode")
    depth = None if keyframe.depth is None else np.asarray(keyframe.depth, np.float32)
    return MapView(int(keyframe.id), np.asarray(keyframe.pose, np.float64), np.asarray(keyframe.K, np.float64),
                   grey, depth)


def views_of_package(package: MapPackage) -> list[MapView]:
    """Every keyframe of `package` as a `MapView`."""
    return [view_of_keyframe(kf) for kf in package.keyframes]
