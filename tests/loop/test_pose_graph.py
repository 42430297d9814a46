"""Sim(3) pose graph (paper eq. 14) on synthetic looping trajectories with known ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worker.geometry import make_sim3, relative_transform, so3_exp
from worker.geometry.gtsam_bridge import sim3_from_gtsam, sim3_to_gtsam
from worker.loop.pose_graph import (
    Sim3PoseGraph,
    propagate_to_frames,
    sim3_batch_from_gtsam,
    sim3_batch_to_gtsam,
)
from worker.loop.synthetic import ate_rmse, make_loop_problem
from worker.serialization import pack, unpack

N = 300


def _optimized(problem) -> np.ndarray:
    result = problem.graph.optimize()
    return np.stack([result.poses[k] for k in range(N)])


def test_correct_loops_cut_ate_by_80_percent():
    problem = make_loop_problem(n=N)
    before = ate_rmse(problem.drifted_poses, problem.gt_poses)
    after = ate_rmse(_optimized(problem), problem.gt_poses)
    assert before > 0.3  # the injected drift is substantial
    assert after <= 0.2 * before


def test_one_false_loop_is_rejected_by_the_robust_kernel():
    clean = ate_rmse(_optimized(make_loop_problem(n=N)), make_loop_problem(n=N).gt_poses)
    problem = make_loop_problem(n=N)
    gt = torch.from_numpy(problem.gt_poses)
    # claims pose 200 coincides with pose 40, which lies on the other side of the circle
    problem.graph.add_edge(40, 200, relative_transform(gt[40], gt[40]), "loop")
    result = problem.graph.optimize()
    est = np.stack([result.poses[k] for k in range(N)])
    assert ate_rmse(est, problem.gt_poses) <= 1.2 * clean
    worst = max(result.loop_residuals, key=result.loop_residuals.get)
    assert worst == (40, 200)


def test_without_robust_kernel_a_false_loop_bends_the_map():
    clean = ate_rmse(_optimized(make_loop_problem(n=N, robust=None)), make_loop_problem(n=N).gt_poses)
    problem = make_loop_problem(n=N, robust=None)
    gt = torch.from_numpy(problem.gt_poses)
    problem.graph.add_edge(40, 200, relative_transform(gt[40], gt[40]), "loop")
    assert ate_rmse(_optimized(problem), problem.gt_poses) > 3 * clean


def test_prior_keeps_first_keyframe_and_scale_drift_is_removed():
    problem = make_loop_problem(n=N)
    est = _optimized(problem)
    np.testing.assert_allclose(est[0], problem.gt_poses[0], atol=1e-6)
    scales = np.cbrt(np.linalg.det(est[:, :3, :3]))
    drifted_scales = np.cbrt(np.linalg.det(problem.drifted_poses[:, :3, :3]))
    assert np.abs(drifted_scales - 1).max() > 0.5
    assert np.abs(scales - 1).max() < 0.1


def test_batched_conversions_match_the_bridge():
    rng = np.random.default_rng(1)
    Ts = np.stack([make_sim3(so3_exp(torch.from_numpy(rng.normal(size=3))), torch.from_numpy(rng.normal(size=3)),
                             float(rng.uniform(0.5, 2))).numpy() for _ in range(5)])
    for T, S in zip(Ts, sim3_batch_to_gtsam(Ts)):
        np.testing.assert_allclose(S.matrix(), sim3_to_gtsam(T).matrix(), atol=1e-12)
        np.testing.assert_allclose(sim3_from_gtsam(S).numpy(), T, atol=1e-12)
    np.testing.assert_allclose(sim3_batch_from_gtsam(sim3_batch_to_gtsam(Ts)), Ts, atol=1e-12)


def test_frames_follow_their_keyframe():
    rng = np.random.default_rng(2)
    old_kf = make_sim3(so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)),
                       torch.tensor([1.0, 0, 0], dtype=torch.float64), 1.5)
    new_kf = make_sim3(so3_exp(torch.tensor([0.0, -0.2, 0.1], dtype=torch.float64)),
                       torch.tensor([0.0, 2, 0], dtype=torch.float64), 0.8)
    frame = old_kf @ make_sim3(so3_exp(torch.from_numpy(rng.normal(size=3) * 0.1)),
                               torch.from_numpy(rng.normal(size=3)))
    out = propagate_to_frames({5: frame.numpy(), 6: np.eye(4)}, {5: 3, 6: 9}, {3: old_kf.numpy()},
                              {3: new_kf.numpy()})
    np.testing.assert_allclose(relative_transform(new_kf, torch.from_numpy(out[5])).numpy(),
                               relative_transform(old_kf, frame).numpy(), atol=1e-10)
    np.testing.assert_allclose(out[6], np.eye(4))


def test_state_dict_round_trips_through_msgpack():
    problem = make_loop_problem(n=40, laps=1.5, n_loops=3)
    graph = Sim3PoseGraph()
    graph.load_state_dict(unpack(pack(problem.graph.state_dict())))
    assert len(graph) == 40 and len(graph.edges) == len(problem.graph.edges)
    a, b = problem.graph.optimize().poses, graph.optimize().poses
    for k in a:
        np.testing.assert_allclose(a[k], b[k], atol=1e-9)


def test_bad_input_is_rejected():
    graph = Sim3PoseGraph()
    with pytest.raises(ValueError, match="empty"):
        graph.optimize()
    graph.add_node(0, np.eye(4))
    with pytest.raises(ValueError, match="no node 1"):
        graph.add_edge(0, 1, np.eye(4))
    graph.add_node(1, np.eye(4))
    with pytest.raises(ValueError, match="edge kind"):
        graph.add_edge(0, 1, np.eye(4), kind="teleport")
    with pytest.raises(ValueError, match="4x4"):
        graph.add_edge(0, 1, np.eye(3))
    with pytest.raises(ValueError, match="robust"):
        Sim3PoseGraph(robust="tukey-ish")
