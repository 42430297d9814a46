"""Frames RGB-D odometry measured against an earlier keyframe the camera came back to are put on that keyframe's
final pose when the session finishes (worker.pipeline.trajectory `anchor_frames`), on real Kinect frames: TUM fr1/xyz
frames 40-87 (tests/data/tum_fr1_xyz_mini, CC BY 4.0) played forward and back."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from worker.config import SlamConfig
from worker.data import open_source
from worker.data.sources.pingpong import sweep_order
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "tum_fr1_xyz_mini"


def test_frames_come_back_to_a_keyframe_end_on_its_final_pose() -> None:
    source = open_source(str(DATA), use_gt_depth=True, use_gt_poses=False)
    recorded = list(source)
    frames = [replace(recorded[p], index=i, timestamp=i / 30) for i, p in enumerate(sweep_order(len(recorded), 2))]
    system = SlamSystem(SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False}), source.intrinsics)
    for frame in frames:
        system.push(frame)
    trajectory = system.tracking_stage.trajectory
    followed = {r.index: (r.keyframe, r.relative.copy()) for r in trajectory.frames}  # as tracking tied them
    system.finish()
    anchored = [r for r in trajectory.frames if r.anchor != -1]
    assert len(anchored) >= 5 and all(r.anchor < r.index and not r.is_keyframe for r in anchored)
    refined = [e for e in system.finish_events if e.TYPE == "poses_refined"]
    assert len(refined) == 1 and refined[0].frames == len(anchored) and refined[0].revision == trajectory.revision
    poses = dict((i, p) for i, _, p in system.trajectory())
    for record in anchored:
        assert np.allclose(poses[record.index], trajectory.keyframe_poses[record.anchor] @ record.anchored)
    # on the anchor the frames are at least as near the motion capture as following their own keyframe left them
    gt = {f.index: f.gt_pose for f in frames}
    final_keyframes = trajectory.keyframe_poses
    rows = [r.index for r in anchored]
    as_followed = np.stack([final_keyframes[followed[i][0]] @ followed[i][1] for i in rows])
    whole = [i for i in poses if i not in rows]  # the alignment comes from the frames anchoring did not touch
    align = np.stack([poses[i] for i in whole]), np.stack([gt[i] for i in whole])
    T = absolute_trajectory_error(*align, "se3").alignment

    def error(estimate: np.ndarray) -> float:
        placed = estimate[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
        return float(np.sqrt(np.mean(np.sum((placed - np.stack([gt[i][:3, 3] for i in rows])) ** 2, axis=1))))

    assert error(np.stack([poses[i] for i in rows])) <= 1.05 * error(as_followed)
    system.close()


def test_posed_rgbd_frames_come_back_to_a_keyframe_are_anchored_in_the_device_world() -> None:
    source = open_source(str(DATA), use_gt_depth=True, use_gt_poses=True)  # the motion capture as the device
    recorded = list(source)
    frames = [replace(recorded[p], index=i, timestamp=i / 30) for i, p in enumerate(sweep_order(len(recorded), 2))]
    config = SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False}, input={"pose_mode": "seeded"})
    system = SlamSystem(config, source.intrinsics)
    for frame in frames:
        system.push(frame)
    system.finish()
    trajectory = system.tracking_stage.trajectory
    anchored = [r for r in trajectory.frames if r.anchor != -1]
    assert len(anchored) >= 5
    poses = dict((i, p) for i, _, p in system.trajectory())
    gt = {f.index: f.gt_pose for f in frames}
    for record in anchored:  # on the anchor, in the device's world and units: near the device's pose
        assert np.allclose(poses[record.index], trajectory.keyframe_poses[record.anchor] @ record.anchored)
        assert np.linalg.norm(poses[record.index][:3, 3] - gt[record.index][:3, 3]) < 0.05
    system.close()
