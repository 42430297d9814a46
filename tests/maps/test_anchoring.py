"""The own-world -> map-world transform: never from one fix, rigid when metric, a similarity when up to scale."""

from __future__ import annotations

import numpy as np
import pytest

from worker.geometry.align import fit_similarity
from worker.maps.anchoring import MapAnchoring
from worker.maps.localizer import MapFix


def _pose(angle: float, axis: int, position: list[float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    R = np.eye(3)
    i, j = [k for k in range(3) if k != axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, position
    return T


def _fix(pose: np.ndarray, inliers: int = 100) -> MapFix:
    return MapFix(pose, view=0, inliers=inliers, matches=150, reprojection_px=1.0, depth_agreement=0.8)


WORLD = _pose(0.7, 1, [1.0, -0.5, 2.0])  # own world -> map world


def test_two_agreeing_fixes_anchor_a_metric_session_one_does_not() -> None:
    anchoring = MapAnchoring(metric=True)
    own = [_pose(0.1 * k, 2, [0.1 * k, 0.0, 0.0]) for k in range(3)]
    assert anchoring.propose(0, own[0], _fix(WORLD @ own[0]), scene_depth=2.0) is None
    transform = anchoring.propose(1, own[1], _fix(WORLD @ own[1], 120), scene_depth=2.0)
    assert transform is not None and np.allclose(transform, WORLD, atol=1e-9)
    assert anchoring.anchored


def test_a_fix_that_disagrees_does_not_anchor() -> None:
    anchoring = MapAnchoring(metric=True)
    own = [_pose(0.0, 2, [0.1 * k, 0.0, 0.0]) for k in range(2)]
    wrong = _pose(0.0, 2, [0.5, 0.0, 0.0]) @ WORLD  # 50 cm off: a false match
    anchoring.propose(0, own[0], _fix(WORLD @ own[0]), scene_depth=2.0)
    assert anchoring.propose(1, own[1], _fix(wrong @ own[1]), scene_depth=2.0) is None
    assert not anchoring.anchored


def _up_to_scale_track(scale: float, frames: int, step: float = 1.0
                       ) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """A similarity of `scale` from an up-to-scale session's world to the map's, the session's own poses over a
    curved path (`step` times as far apart) and the same poses in the map (rigid)."""
    similarity = WORLD.copy()
    similarity[:3, :3] *= scale
    own = [_pose(0.05 * k * step, 0, [0.4 * k * step, 0.1 * (k * step) ** 2, 0.0]) for k in range(frames)]
    in_map = []
    for T in own:
        rigid = similarity @ T
        rigid[:3, :3] /= scale
        in_map.append(rigid)
    return similarity, own, in_map


def test_an_up_to_scale_session_meets_the_map_by_a_similarity() -> None:
    similarity, own, in_map = _up_to_scale_track(0.37, 4)
    assert np.allclose(fit_similarity(own, in_map), similarity, atol=1e-9)
    anchoring = MapAnchoring(metric=False, agreeing=3)
    results = [anchoring.propose(k, T, _fix(M), scene_depth=1.0) for k, (T, M) in enumerate(zip(own, in_map))]
    assert results[0] is None and results[1] is None  # two fixes measure a scale but nothing checks it
    assert results[2] is not None and np.allclose(results[2], similarity, atol=1e-9)


def test_a_similarity_is_found_past_one_fix_that_does_not_fit() -> None:
    """An up-to-scale session's early fix whose own pose was off (the odometry not settled) no longer keeps the
    others from agreeing; with it alone against one other, nothing anchors."""
    similarity, own, in_map = _up_to_scale_track(0.5, 5)
    off = own[0].copy()
    off[:3, 3] += [0.0, 0.3, 0.0]  # its own pose 30 cm (15 cm in the map) from where the others put it
    anchoring = MapAnchoring(metric=False, agreeing=3)
    assert anchoring.propose(0, off, _fix(in_map[0]), scene_depth=1.0) is None
    assert anchoring.propose(1, own[1], _fix(in_map[1]), scene_depth=1.0) is None
    assert anchoring.propose(2, own[2], _fix(in_map[2]), scene_depth=1.0) is None  # the off one and two others
    found = anchoring.propose(3, own[3], _fix(in_map[3]), scene_depth=1.0)
    assert found is not None and np.allclose(found, similarity, atol=1e-9)


def test_two_fixes_whose_depth_measured_the_scale_anchor_an_up_to_scale_session_without_a_baseline() -> None:
    """Fixes with the scale the frames' own points measured against the map's depth: two of different frames
    that agree anchor at once, the camera hardly moved; a scale 10 % off does not agree."""
    similarity, near, near_in_map = _up_to_scale_track(0.5, 3, step=0.01)  # 4 mm apart: no baseline
    anchoring = MapAnchoring(metric=False, agreeing=3)
    assert anchoring.propose(0, near[0], _fix(near_in_map[0]), scene_depth=1.0, scale=0.5) is None
    assert anchoring.propose(1, near[1], _fix(near_in_map[1]), scene_depth=1.0, scale=0.55) is None  # 10 % off
    found = anchoring.propose(2, near[2], _fix(near_in_map[2]), scene_depth=1.0, scale=0.501)
    assert found is not None
    assert np.cbrt(np.linalg.det(found[:3, :3])) == pytest.approx(0.5, rel=0.01)
    assert np.allclose(found @ near[2][:, 3], similarity @ near[2][:, 3], atol=1e-3)
    restored = MapAnchoring(metric=False, agreeing=3)
    restored.load_state_dict(anchoring.state_dict())
    assert [o.scale for o in restored.observations] == [0.5, 0.55, 0.501]
    without = MapAnchoring(metric=False, agreeing=3)  # the same fixes without a scale: no baseline, no anchoring
    assert all(without.propose(k, T, _fix(M), scene_depth=1.0) is None
               for k, (T, M) in enumerate(zip(near, near_in_map)))


def test_the_anchoring_survives_its_state() -> None:
    anchoring = MapAnchoring(metric=True)
    own = [_pose(0.0, 2, [0.1 * k, 0.0, 0.0]) for k in range(2)]
    anchoring.propose(0, own[0], _fix(WORLD @ own[0]), scene_depth=2.0)
    restored = MapAnchoring(metric=True)
    restored.load_state_dict(anchoring.state_dict())
    assert restored.propose(1, own[1], _fix(WORLD @ own[1]), scene_depth=2.0) is not None


def test_one_fix_the_frames_depth_confirms_anchors_alone() -> None:
    own = _pose(0.0, 2, [0.1, 0.0, 0.0])
    confirmed = MapFix(WORLD @ own, view=0, inliers=150, matches=200, reprojection_px=1.0, depth_agreement=0.95)
    assert np.allclose(MapAnchoring(metric=True).propose(0, own, confirmed, scene_depth=2.0), WORLD)
    without_depth = MapFix(WORLD @ own, view=0, inliers=150, matches=200, reprojection_px=1.0,
                           depth_agreement=None)
    assert MapAnchoring(metric=True).propose(0, own, without_depth, scene_depth=2.0) is None
    assert MapAnchoring(metric=False).propose(0, own, confirmed, scene_depth=2.0) is None  # a scale to measure
