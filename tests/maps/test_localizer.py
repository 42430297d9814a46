"""Finding real frames in a stored map: verified fixes near the ground truth, none in another scene."""

from __future__ import annotations

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
