"""Finding real frames in a stored map: verified fixes near the ground truth, none in another scene."""

from __future__ import annotations

import cv2
import numpy as np

from worker.maps.localizer import MapLocalizer

from .conftest import camera_matrix, gray, views_of


def test_frames_between_the_maps_keyframes_are_found_near_their_true_pose(icl_frames) -> None:
    localizer = MapLocalizer(views_of(icl_frames[::4]))
    queries = [f for f in icl_frames if f.index % 4 == 2]
    errors = []
    for frame in queries:
        fix = localizer.locate(gray(frame), camera_matrix(frame), frame.depth)
        if fix is not None:
            errors.append(np.linalg.norm(fix.pose[:3, 3] - frame.gt_pose[:3, 3]))
            assert fix.inliers >= localizer.settings.min_inliers
            assert fix.depth_agreement is not None and fix.depth_agreement >= localizer.settings.min_depth_agreement
    assert len(errors) >= 0.6 * len(queries)
    assert np.median(errors) < 0.03 and max(errors) < 0.10


def test_another_scene_is_never_located(icl_frames, other_scene_frames) -> None:
    localizer = MapLocalizer(views_of(icl_frames[::2]))
    for frame in other_scene_frames:
        assert localizer.locate(gray(frame), camera_matrix(frame), frame.depth) is None
        assert localizer.locate(gray(frame), camera_matrix(frame)) is None  # without depth to check against


def test_views_without_depth_are_no_places(icl_frames) -> None:
    views = views_of(icl_frames[:3])
    views[1].depth = None
    assert len(MapLocalizer(views)) == 2


def test_a_camera_of_another_resolution_is_found_in_the_map(icl_frames) -> None:
    """The map's places are world points: a frame of half the size (its own camera matrix) matches them too."""
    localizer = MapLocalizer(views_of(icl_frames[::4]))
    found = 0
    for frame in [f for f in icl_frames if f.index % 4 == 2][:8]:
        small = cv2.resize(gray(frame), (frame.width // 2, frame.height // 2), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(frame.depth, (frame.width // 2, frame.height // 2), interpolation=cv2.INTER_NEAREST)
        K = camera_matrix(frame).copy()
        K[:2] *= 0.5
        fix = localizer.locate(small, K, depth)
        if fix is not None:
            found += 1
            assert np.linalg.norm(fix.pose[:3, 3] - frame.gt_pose[:3, 3]) < 0.05
    assert found >= 4
