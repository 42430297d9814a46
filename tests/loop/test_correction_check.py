"""A pose-graph solve that diverged moves nothing (worker.loop.correction_check): the loop stage gives the item up,
puts its graph back as it was before the item's edges, and the next item solves as if it had never come."""

from __future__ import annotations

import numpy as np
from test_pose_graph_map_join import NEW_SCALE, RESTART, _scaled, _stage, _tracked, _truth

from worker.events import MapsMerged
from worker.loop.correction_check import implausible_correction
from worker.loop.pose_graph import PoseGraphResult
from worker.pipeline.loop_stage import MapJoin


def _sim3(scale: float, t: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] *= scale
    pose[:3, 3] = t
    return pose


def test_implausible_solutions_are_named():
    before = {0: _sim3(1.0), 1: _sim3(1.0, 0.5)}
    assert implausible_correction(before, {0: _sim3(1.0), 1: _sim3(1.1, 0.6)}, metric=True) is None
    assert implausible_correction(before, {1: _sim3(2.0)}, metric=False) is None  # a monocular map's rescale
    assert "scale" in implausible_correction(before, {1: _sim3(2.0)}, metric=True)
    assert "scale" in implausible_correction(before, {1: _sim3(1e8, 2e6)}, metric=False)  # seen on TUM fr1/xyz
    assert "not finite" in implausible_correction(before, {1: np.full((4, 4), np.nan)}, metric=False)
    mirrored = _sim3(1.0)
    mirrored[0, 0] = -1.0
    assert "proper" in implausible_correction(before, {0: mirrored}, metric=False)
    assert implausible_correction(before, {7: _sim3(3.0)}, metric=True) is None  # a new node has no scale before


def test_a_diverged_solve_moves_nothing_and_the_graph_stays_as_it_was():
    truth = _truth()
    stage = _stage(_tracked(truth))
    nodes_before = {k: v.copy() for k, v in stage.pose_graph.nodes.items()}
    edges_before = len(stage.pose_graph.edges)
    solve = stage.pose_graph.optimize

    def diverged(**_options) -> PoseGraphResult:
        for key in stage.pose_graph.nodes:  # the solve wrote its garbage into the graph, as a real one does
            stage.pose_graph.nodes[key] = _sim3(1e8, 2e6)
        return PoseGraphResult({k: _sim3(1e8, 2e6) for k in nodes_before}, 1.0, 1e12, 50)

    stage.pose_graph.optimize = diverged
    relative = np.linalg.inv(truth[3]) @ _scaled(truth[19], 1 / NEW_SCALE)
    stage.submit(MapJoin(3, 19, relative, MapsMerged()))
    assert stage.take_corrections() == [] and stage.solves_given_up == 1
    assert len(stage.pose_graph.edges) == edges_before  # the join's edge went with it
    for key, pose in nodes_before.items():
        np.testing.assert_allclose(stage.pose_graph.nodes[key], pose)
    stage.pose_graph.optimize = solve  # the same join again, with a solve that works, is applied
    stage.submit(MapJoin(3, 19, relative, MapsMerged()))
    [correction] = stage.take_corrections()
    assert np.linalg.norm(correction.poses[19][:3, 3] - truth[19][:3, 3]) < 0.02
    assert len(stage.pose_graph.edges) == edges_before + 1 and RESTART < 19
