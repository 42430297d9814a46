"""Visual odometry's final bundle adjustment (worker.tracking.global_adjustment) on real frames: points seen again
on a revisit are joined to the first visit's and every keyframe is adjusted at once. TUM fr1/xyz frames 40-87
(tests/data/tum_fr1_xyz_mini, CC BY 4.0) and ICL-NUIM living room 1 (tests/data/icl_mini, CC BY 3.0), played
forward and back so that the camera comes back."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from worker.data import open_source
from worker.data.sources.pingpong import sweep_order
from worker.eval import absolute_trajectory_error
from worker.tracking.keyframe_archive import ArchivedKeyframe, KeyframeArchive
from worker.tracking.local_map import LocalMap
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig

DATA = Path(__file__).parents[1] / "data"


def _odometry_over(name: str, sweeps: int, config: VisualOdometryConfig | None = None):
    source = open_source(str(DATA / name))
    recorded = list(source)
    frames = [replace(recorded[p], index=i, timestamp=i / 30)
              for i, p in enumerate(sweep_order(len(recorded), sweeps))]
    odometry = VisualOdometry(config)
    for frame in frames:
        odometry.track(frame, source.intrinsics)
    return odometry, {f.index: f.gt_pose for f in frames}


def _keyframe_ate(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float:
    keys = sorted(poses)
    return absolute_trajectory_error(np.stack([poses[k] for k in keys]), np.stack([truth[k] for k in keys]),
                                     "sim3").rmse


@pytest.mark.parametrize(("name", "sweeps"), [("icl_mini", 2), ("tum_fr1_xyz_mini", 3)])
def test_coming_back_joins_points_and_brings_the_keyframes_nearer_the_truth(name: str, sweeps: int) -> None:
    odometry, truth = _odometry_over(name, sweeps)
    corrections = odometry.keyframe_corrections()
    result = odometry.final_adjustment
    assert result.local_scales is not None and result.local_scales[0] <= result.local_scales[2]
    assert result.pairs >= odometry.config.fuse_min_pairs and result.joined > 0
    keyframes = odometry.state.archive.keyframes
    archived = {k: kf.pose for k, kf in keyframes.items()}  # after the windowed adjustments
    given = {k: kf.pose if kf.handed_out is None else kf.handed_out for k, kf in keyframes.items()}
    assert set(corrections) == set(archived) and len(archived) >= 10
    assert sum(kf.handed_out is not None for kf in keyframes.values()) >= len(keyframes) - 2
    for correction in corrections.values():  # similarities: the local scale the adjustment found comes along
        scale = np.cbrt(np.linalg.det(correction[:3, :3]))
        assert 0.7 < scale < 1.4
        assert np.allclose(correction[:3, :3] @ correction[:3, :3].T, scale**2 * np.eye(3), atol=1e-9)
    adjusted = {k: corrections[k] @ pose for k, pose in given.items()}
    oldest = min(adjusted)
    assert np.allclose(adjusted[oldest][:3, 3], archived[oldest][:3, 3])  # the oldest keyframe holds the gauge
    assert _keyframe_ate(adjusted, truth) < 0.97 * _keyframe_ate(archived, truth)


def test_one_pass_without_revisits_keeps_its_poses() -> None:
    odometry, _ = _odometry_over("tum_fr1_xyz_mini", 1)
    assert odometry.keyframe_corrections() == {}
    assert odometry.final_adjustment.pairs < odometry.config.fuse_min_pairs


def test_off_archives_nothing_and_adjusts_nothing() -> None:
    odometry, _ = _odometry_over("tum_fr1_xyz_mini", 2, VisualOdometryConfig(final_adjustment=False))
    assert len(odometry.state.archive) == 0 and odometry.keyframe_corrections() == {}


def test_the_archive_is_bounded_and_keyframes_of_two_maps_are_not_adjusted_together() -> None:
    def keyframe(index: int) -> ArchivedKeyframe:
        empty = np.zeros(0, np.int64)
        return ArchivedKeyframe(index, np.eye(4), np.zeros((0, 2), np.float32), empty, empty,
                                np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), empty)

    archive = KeyframeArchive(max_keyframes=3)
    for index in range(5):
        archive.record(keyframe(index), {index: np.zeros(3)}, map_token=7)
    assert [k.index for k in archive.ordered()] == [2, 3, 4] and not archive.mixed_maps
    archive.record(keyframe(5), {}, map_token=8)
    assert archive.mixed_maps


def test_point_ids_stay_with_their_points_through_forgetting_and_snapshots() -> None:
    local = LocalMap()
    local.add_points(np.arange(12.0).reshape(4, 3), np.zeros((4, 32), np.uint8))
    local.forget(np.array([True, False, True, False]))
    local.add_points(np.ones((1, 3)), np.zeros((1, 32), np.uint8))
    assert local.ids.tolist() == [1, 3, 4] and np.allclose(local.positions[1], [9.0, 10.0, 11.0])
    again = LocalMap.from_state(local.to_state())
    assert again.ids.tolist() == [1, 3, 4] and again.next_id == 5
    old = local.to_state()
    del old["ids"], old["next_id"]  # a snapshot from before point ids
    assert LocalMap.from_state(old).ids.tolist() == [0, 1, 2]
