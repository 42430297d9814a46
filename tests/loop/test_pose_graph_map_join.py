"""Two maps joined in the loop stage's pose graph by a Sim(3) edge, on constructed keyframe poses: a map restarted at
half the old map's scale is brought back to the old map's frame and scale, and its seam edge gives way."""

from __future__ import annotations

import cv2
import numpy as np

from worker.config import LoopConfig
from worker.events import MapsMerged
from worker.loop.pose_graph import Sim3PoseGraph
from worker.pipeline.loop_stage import GraphKeyframe, LoopClosingStage, MapJoin

RESTART = 10  # keyframes 0-9: the old map; 10-19: the restarted one
NEW_SCALE = 0.5  # the restarted map's units: half the old map's


def _truth() -> list[np.ndarray]:
    """20 keyframes on an arc around a room, camera-to-world, in the old map's units."""
    poses = []
    for k in range(20):
        angle = 0.3 * k
        pose = np.eye(4)
        pose[:3, :3] = cv2.Rodrigues(np.array([0.0, angle, 0.05 * np.sin(k)]))[0]
        pose[:3, 3] = [2.0 * np.sin(angle), 0.1 * k, 2.0 * (1 - np.cos(angle))]
        poses.append(pose)
    return poses


def _tracked(truth: list[np.ndarray]) -> list[np.ndarray]:
    """What odometry hands out: the old map exact; the restarted map continues from keyframe 9's pose (the anchor)
    but measures distances in its own units (NEW_SCALE)."""
    out = [p.copy() for p in truth[:RESTART]]
    for k in range(RESTART, len(truth)):
        step = np.linalg.inv(truth[k - 1]) @ truth[k]
        step[:3, 3] *= NEW_SCALE
        out.append(out[-1] @ step)
    return out


def _scaled(pose: np.ndarray, scale: float) -> np.ndarray:
    out = pose.copy()
    out[:3, :3] *= scale
    return out


def _stage(tracked: list[np.ndarray]) -> LoopClosingStage:
    stage = LoopClosingStage(LoopConfig(), Sim3PoseGraph(), None, None, metric=False, threaded=False)
    stage.submit(GraphKeyframe(0, tracked[0]))
    for k in range(1, len(tracked)):
        relative = np.linalg.inv(tracked[k - 1]) @ tracked[k]
        stage.submit(GraphKeyframe(k, tracked[k], k - 1, relative, "restart" if k == RESTART else "sequential"))
    return stage


def test_a_sim3_edge_brings_the_restarted_map_into_the_old_frame_and_scale():
    truth = _truth()
    tracked = _tracked(truth)
    stage = _stage(tracked)
    # Keyframe 19 recognised keyframe 3 of the old map: their relative pose, keyframe 19 in its own units.
    relative = np.linalg.inv(truth[3]) @ _scaled(truth[19], 1 / NEW_SCALE)
    stage.submit(MapJoin(3, 19, relative, MapsMerged(place=3)))
    corrections = stage.take_corrections()
    assert len(corrections) == 1 and corrections[0].event.TYPE == "maps_merged"
    assert corrections[0].event.to_keyframe == 3 and corrections[0].event.from_keyframe == 19
    poses = corrections[0].poses
    before = max(np.linalg.norm(tracked[k][:3, 3] - truth[k][:3, 3]) for k in range(RESTART, 20))
    after = max(np.linalg.norm(poses[k][:3, 3] - truth[k][:3, 3]) for k in range(20))
    assert before > 1.0 and after < 0.02  # every keyframe where it truly was
    for k in range(RESTART, 20):  # the restarted keyframes carry the scale of their units
        assert abs(np.cbrt(np.linalg.det(poses[k][:3, :3])) - 1 / NEW_SCALE) < 0.02
    for k in range(RESTART):
        np.testing.assert_allclose(poses[k], truth[k], atol=5e-3)  # the old map stays (it bends a little)
    kinds = [e.kind for e in stage.pose_graph.edges]
    assert kinds.count("restart") == 1 and kinds.count("map_join") == 1


def test_a_join_between_unknown_keyframes_is_ignored():
    tracked = _tracked(_truth())
    stage = _stage(tracked)
    stage.submit(MapJoin(3, 25, np.eye(4), MapsMerged()))
    assert stage.take_corrections() == [] and all(e.kind != "map_join" for e in stage.pose_graph.edges)
