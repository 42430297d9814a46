"""A map package keeps each keyframe's places (what relocalizing in it needs), so that a session in the map locates
frames without describing the map's keyframes first; a package with broken places is refused."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from protocol.map_package import MapKeyframe, MapPackage, MapPackageError, decode_package, encode_package
from worker.maps.localizer import MapLocalizer
from worker.maps.views import views_of_package, with_places

from .conftest import camera_matrix, gray


def _keyframe(frame) -> MapKeyframe:
    bgr = cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)
    half = frame.depth[::2, ::2].astype(np.float16)
    return MapKeyframe(id=frame.index, pose=np.asarray(frame.gt_pose, np.float64), K=camera_matrix(frame),
                       width=frame.width, height=frame.height, jpeg=cv2.imencode(".jpg", bgr)[1].tobytes(),
                       depth=half)


def _package(frames, keyframes) -> MapPackage:
    from map_samples import surfels_ply

    ids = [kf.id for kf in keyframes]
    return MapPackage(name="icl", keyframes=keyframes, surfels_ply=surfels_ply(50, ids), scale="metric", mode="rgbd")


def test_places_travel_with_the_package_and_locate_frames(icl_frames) -> None:
    keyframes = with_places([_keyframe(f) for f in icl_frames[::4]])
    assert all(kf.places is not None and len(kf.places["points"]) >= 40 for kf in keyframes)
    package = decode_package(encode_package(_package(icl_frames, keyframes)))
    views = views_of_package(package)
    assert all(v.place is not None and v.gray is None for v in views)  # nothing described, no image decoded
    localizer = MapLocalizer(views)
    frame = icl_frames[6]
    fix = localizer.locate(gray(frame), camera_matrix(frame), frame.depth)
    assert fix is not None and np.linalg.norm(fix.pose[:3, 3] - frame.gt_pose[:3, 3]) < 0.03


def test_broken_places_are_refused(icl_frames) -> None:
    keyframes = with_places([_keyframe(f) for f in icl_frames[:2]])
    places = dict(keyframes[0].places)
    places["points"] = places["points"][:-1]  # one point short of its keypoints
    broken = [replace(keyframes[0], places=places), keyframes[1]]
    with pytest.raises(MapPackageError, match="places points"):
        encode_package(_package(icl_frames, broken))
