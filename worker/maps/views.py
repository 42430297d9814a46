"""A map package's keyframes as the localizer sees them: grey image, depth in the keyframe's units, pose and camera."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from protocol.map_package import MapKeyframe, MapPackage

from .localizer import MapView, describe_view, place_arrays, place_from_arrays


def view_of_keyframe(keyframe: MapKeyframe) -> MapView:
    """One keyframe as a `MapView`: its image decoded when first needed, its place as packaged (else described
    from the image), its depth at the package's half resolution (the localizer reads it at its keypoints and
    brings it to the image's size where it aligns)."""
    depth = None if keyframe.depth is None else np.asarray(keyframe.depth, np.float32)
    pose = np.asarray(keyframe.pose, np.float64)
    place = None if keyframe.places is None else place_from_arrays(keyframe.id, pose, keyframe.places)
    return MapView(int(keyframe.id), pose, np.asarray(keyframe.K, np.float64), None, depth, jpeg=keyframe.jpeg,
                   place=place)


def with_places(keyframes: list[MapKeyframe]) -> list[MapKeyframe]:
    """The keyframes with their places described (what sessions relocalizing in the map would otherwise make
    at their start)."""
    out = []
    for keyframe in keyframes:
        place = describe_view(view_of_keyframe(replace(keyframe, places=None)))
        out.append(replace(keyframe, places=None if place is None else place_arrays(place)))
    return out


def views_of_package(package: MapPackage) -> list[MapView]:
    """Every keyframe of `package` as a `MapView`."""
    return [view_of_keyframe(kf) for kf in package.keyframes]
