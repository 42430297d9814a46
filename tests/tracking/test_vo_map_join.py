"""Joining a map visual odometry restarted after a loss to the older map, by a Sim(3) measured where a keyframe of
the new map recognises a place of the old one: on constructed geometry (exact), and on a rendered synthetic room
whose camera is lost at a 4-frame gap, restarts at a wrong scale and comes back to its start."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.config import SlamConfig
from worker.data import open_source
from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.slam import SlamSystem
from worker.tracking.features import Features
from worker.tracking.map_join import link_maps, moved_points, moved_pose, similarity, similarity_inverse
from worker.tracking.projection import camera_matrix, project
from worker.tracking.relocalization import Place, PlaceRecognizer
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig

CAMERA = Intrinsics(fx=250.0, fy=250.0, cx=160.0, cy=120.0, width=320, height=240)


def _pose(rotvec: tuple[float, float, float], position: tuple[float, float, float]) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = cv2.Rodrigues(np.array(rotvec, np.float64))[0], position
    return pose


def test_a_recognised_place_gives_the_similarity_between_the_two_maps():
    rng = np.random.default_rng(3)
    K = camera_matrix(CAMERA)
    world = rng.uniform([-2, -1.5, 3], [2, 1.5, 6], (200, 3))  # the old map's points, in its units
    place_pose = _pose((0.0, 0.05, 0.0), (0.1, 0.0, 0.0))
    uv_place, _ = project(world, place_pose, K)
    descriptors = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    place = Place(7, place_pose, uv_place.astype(np.float32), descriptors, world, map_id=0)
    # The new map: the same scene in other coordinates, at 0.4 times the old scale, seen from a nearby keyframe.
    truth = similarity(cv2.Rodrigues(np.array([0.1, -0.3, 0.2]))[0], np.array([1.0, -2.0, 0.5]), 1 / 0.4)
    new_from_old = similarity_inverse(truth)
    keyframe_old = _pose((0.02, -0.04, 0.01), (0.3, 0.1, 0.2))
    keyframe = moved_pose(new_from_old, keyframe_old)
    uv, _ = project(world, keyframe_old, K)
    points = moved_points(new_from_old, world)
    points[::3] = np.nan  # not every keypoint lies on one of the new map's points
    features = Features(uv.astype(np.float32), descriptors, np.zeros(200, np.int32))
    config = VisualOdometryConfig()
    link = link_maps(PlaceRecognizer(config), features, points, keyframe, [place], K, np.ones(200),
                     min_inliers=30, min_pairs=10, max_spread=0.15)
    assert link is not None and link.place is place
    assert link.scale == pytest.approx(1 / 0.4, rel=1e-3)
    np.testing.assert_allclose(link.transform, truth, atol=1e-3)
    np.testing.assert_allclose(moved_pose(link.transform, keyframe), keyframe_old, atol=1e-4)
    assert link.pairs == int(np.isfinite(points).all(axis=1).sum())
    # Depth ratios that disagree (a wrong place, a broken map) give no link.
    points *= rng.uniform(0.5, 2.0, (200, 1))
    assert link_maps(PlaceRecognizer(config), features, points, keyframe, [place], K, np.ones(200), 30, 10,
                     0.15) is None


def _scale(estimate: np.ndarray, truth: np.ndarray) -> float:
    """The scale of the best similarity from estimated to true positions [N, 3] (Umeyama)."""
    a, b = estimate - estimate.mean(0), truth - truth.mean(0)
    return float(np.linalg.svd(b.T @ a)[1].sum() / (a ** 2).sum())


@pytest.fixture(scope="module")
def gap_sequence() -> list[Frame]:
    """Room 10003's 90-frame path (it comes back to its start) with frames 30-33 left out: tracking is lost."""
    source = open_source("synthetic://seed=10003?frames=90", use_gt_depth=False)
    frames = [source.frame(n) for n in [*range(30), *range(34, 90)]]
    return [Frame(n, n / 30.0, f.image, f.intrinsics, gt_pose=f.gt_pose) for n, f in enumerate(frames)]


def test_a_restarted_map_is_joined_to_the_old_one_at_the_right_scale(gap_sequence):
    vo = VisualOdometry()
    results = []
    for n, frame in enumerate(gap_sequence):
        results.append(vo.track(frame, frame.intrinsics))
        if n == 60:
            restored = VisualOdometry()
            restored.load_state_dict(unpack(pack(vo.state_dict())))
            assert restored.join is not None and restored.map_id == vo.map_id == 1
    events = [(n, e) for n, r in enumerate(results) for e in r.events]
    restart = next(n for n, e in events if getattr(e, "method", None) == "reinitialized")
    merged = [(n, e) for n, e in events if e.TYPE == "maps_merged"]
    assert restart == 30 and len(merged) == 1
    at, event = merged[0]
    assert event.since == restart and event.place < restart < at  # linked to a keyframe of the old map
    assert vo.join is None and vo.map_id == 0  # the restarted map is part of the old one now
    poses = np.stack([r.pose for r in results])
    assert all(r.tracked for r in results[restart:])
    # Poses handed out never jump at the join: the output carries on from the frame before.
    step = np.linalg.norm(np.diff(poses[restart:, :3, 3], axis=0), axis=1)
    assert step[at - restart - 1] < 3 * np.median(step)
    truth = np.stack([f.gt_pose for f in gap_sequence])[:, :3, 3]
    old = _scale(poses[:restart, :3, 3], truth[:restart])
    seam = _scale(poses[restart:, :3, 3], truth[restart:]) / old
    correction = np.asarray(event.correction)
    joined = np.stack([moved_pose(correction, p) for p in poses[restart:]])
    ratio = _scale(joined[:, :3, 3], truth[restart:]) / old
    assert abs(np.log(seam)) > np.log(1.5)  # the restart guessed the scale badly ...
    assert abs(np.log(ratio)) < np.log(1.15)  # ... the join brings it to the old map's
    assert event.scale == pytest.approx(seam / ratio, rel=1e-6)
    # The edge for the pose graph: the joined frame in the place's frame, in the units each was handed out in (the
    # place's pose as bundle adjustment left it, a little off the pose handed out when it was tracked).
    place = poses[event.place]
    relative = np.asarray(event.relative)
    np.testing.assert_allclose(place @ relative, correction @ poses[at], atol=0.02)


def test_the_engine_joins_the_two_maps_in_its_pose_graph(gap_sequence):
    """The engine adds the join as a Sim(3) edge (the restart's seam edge is loose in scale), solves, and the new
    map's keyframes and frames move into the old map's frame, scale included (`maps_merged` with the revision)."""
    config = SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False})
    system = SlamSystem(config, gap_sequence[0].intrinsics)
    events = [e for frame in gap_sequence for e in system.push(frame).events]
    system.finish()
    events += system.finish_events
    merged = [e for e in events if e.TYPE == "maps_merged"]
    assert len(merged) == 1 and merged[0].revision >= 1 and merged[0].to_keyframe < 30
    kinds = [e.kind for e in system.pose_graph.edges]
    assert kinds.count("restart") == 1 and kinds.count("map_join") == 1
    poses = np.stack([p for _, _, p in system.trajectory()])[:, :3, 3]
    truth = np.stack([f.gt_pose for f in gap_sequence])[:, :3, 3]
    ratio = _scale(poses[30:], truth[30:]) / _scale(poses[:30], truth[:30])
    assert abs(np.log(ratio)) < np.log(1.15)
    system.close()
