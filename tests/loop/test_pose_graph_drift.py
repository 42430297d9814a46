"""A monocular odometry's scale drift corrected between loops: the loop stage solves its pose graph with the device's
keyframe priors every few priors (`drift_corrected`), on constructed keyframe poses. The keyframes move to the
device's positions, and their scale grows where the odometry's shrank, so that each keyframe's part of the map is
brought to the device's scale too."""

from __future__ import annotations

import numpy as np
import torch

from worker.config import LoopConfig
from worker.geometry import sim3_decompose
from worker.loop.pose_graph import EdgeSigmas, PosePrior, Sim3PoseGraph
from worker.loop.synthetic import shrinking_odometry
from worker.pipeline.loop_stage import GraphKeyframe, LoopClosingStage
from worker.tracking.seeded import DRIFT_PRIOR_LOG_SCALE_SIGMA

KEYFRAMES = 24
SHRINK = 0.99  # the odometry's unit shrinks 1 % a keyframe


def _truth() -> list[np.ndarray]:
    """Keyframes 1 m apart on a wide curve (the device's poses), camera-to-world."""
    poses = []
    for k in range(KEYFRAMES):
        yaw = 0.05 * k
        pose = np.eye(4)
        pose[:3, :3] = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        pose[:3, 3] = [20.0 * (1 - np.cos(yaw)), 0.0, 20.0 * np.sin(yaw)]
        poses.append(pose)
    return poses


def _tracked(truth: list[np.ndarray]) -> list[np.ndarray]:
    """The odometry's keyframe poses: the true rotations, each step SHRINK times shorter than the one before."""
    return shrinking_odometry(truth, SHRINK)


def _run(solve_every: int) -> tuple[LoopClosingStage, list]:
    truth, tracked = _truth(), _tracked(_truth())
    stage = LoopClosingStage(LoopConfig(), Sim3PoseGraph(), None, None, metric=False, threaded=False,
                             solve_priors_every=solve_every)
    sigmas = EdgeSigmas(np.radians(2.0), 0.1, DRIFT_PRIOR_LOG_SCALE_SIGMA)
    for k in range(KEYFRAMES):
        previous = None if k == 0 else k - 1
        relative = None if k == 0 else np.linalg.inv(tracked[k - 1]) @ tracked[k]
        stage.submit(GraphKeyframe(k, tracked[k], previous, relative, scene_depth=10.0))
        stage.submit(PosePrior(k, truth[k], sigmas))
    return stage, stage.take_corrections()


def test_the_graph_solved_with_device_priors_brings_a_drifting_odometry_to_the_device() -> None:
    truth, tracked = _truth(), _tracked(_truth())
    _, corrections = _run(solve_every=4)
    assert len(corrections) == KEYFRAMES // 4
    assert all(c.event.TYPE == "drift_corrected" for c in corrections)
    assert [c.event.keyframe for c in corrections] == list(range(3, KEYFRAMES, 4))
    final = corrections[-1].poses
    before = max(np.linalg.norm(tracked[k][:3, 3] - truth[k][:3, 3]) for k in range(KEYFRAMES))
    after = max(np.linalg.norm(final[k][:3, 3] - truth[k][:3, 3]) for k in range(KEYFRAMES))
    assert before > 2.0 and after < 0.1 * before
    # The last keyframe's odometry unit is SHRINK**23 (0.79) of the first's: the keyframes' scale grows with the
    # drift (part of the stretch stays in the edges' translations, which the graph weighs against their scale)
    scales = [_scale(final[k]) for k in range(KEYFRAMES)]
    assert abs(scales[0] - 1.0) < 0.01 and np.all(np.diff(scales) > -1e-4)
    assert 1 + 0.4 * (1 / SHRINK ** 23 - 1) < scales[-1] < 1 / SHRINK ** 23 + 0.05


def _scale(pose: np.ndarray) -> float:
    return float(sim3_decompose(torch.from_numpy(pose))[0])


def test_without_solving_between_loops_priors_wait_for_a_loop() -> None:
    stage, corrections = _run(solve_every=0)
    assert corrections == [] and stage.priors_unsolved == KEYFRAMES
