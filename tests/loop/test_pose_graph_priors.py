"""Absolute priors in the Sim(3) pose graph (device poses of keyframes, pose_mode seeded): they pull drifted nodes
towards the measured poses in proportion to their uncertainty, the incremental solve agrees with the batch one, a
gross prior is down-weighted by the robust kernel, and priors survive a snapshot."""

from __future__ import annotations

import numpy as np

from protocol.codec import pack, unpack
from worker.loop.pose_graph import EdgeSigmas, Sim3PoseGraph

N = 12


def _translation(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, 0.0]
    return T


def _chain(graph: Sim3PoseGraph, drift: float = 0.01) -> list[np.ndarray]:
    """A straight walk of N keyframes 0.1 apart whose odometry over-reads each step by `drift`; returns the truth."""
    truth = [_translation(0.1 * k) for k in range(N)]
    for k in range(N):
        graph.add_node(k, _translation((0.1 + drift) * k))
        if k:
            graph.add_edge(k - 1, k, _translation(0.1 + drift))
    return truth


def _error(poses: dict[int, np.ndarray], truth: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean([np.sum((poses[k][:3, 3] - t[:3, 3]) ** 2) for k, t in enumerate(truth)])))


def _graph(**kwargs) -> Sim3PoseGraph:
    return Sim3PoseGraph(sigmas={"sequential": EdgeSigmas(0.01, 0.02, 1e-4)}, **kwargs)


def test_priors_pull_a_drifted_chain_towards_the_measured_poses() -> None:
    plain = _graph()
    truth = _chain(plain)
    drifted = _error(plain.optimize().poses, truth)
    tight, loose = _graph(), _graph()
    for graph, sigma in ((tight, 0.005), (loose, 0.5)):
        _chain(graph)
        for k in range(1, N, 3):
            graph.add_prior(k, truth[k], EdgeSigmas(0.01, sigma, 1e-3))
    assert drifted > 0.03
    assert _error(tight.optimize().poses, truth) < 0.2 * drifted
    assert _error(loose.optimize().poses, truth) > 0.8 * drifted  # a loose prior barely moves the odometry


def test_incremental_priors_agree_with_the_batch_solve() -> None:
    incremental = _graph()
    truth = _chain(incremental)
    incremental.optimize()  # seeds iSAM2; the priors below go in incrementally
    for k in range(2, N, 3):
        incremental.add_prior(k, truth[k], EdgeSigmas(0.01, 0.01, 1e-3))
    assert incremental.flush()
    result = incremental.optimize()
    assert result.solver == "incremental"
    batch = incremental.optimize_full(update=False)
    for k in range(N):
        np.testing.assert_allclose(result.poses[k], batch.poses[k], atol=2e-4)


def test_a_gross_prior_is_down_weighted_and_priors_survive_a_snapshot() -> None:
    graph = _graph(robust="cauchy", robust_k=1.0)
    truth = _chain(graph, drift=0.0)
    graph.add_prior(6, _translation(0.6, 2.0), EdgeSigmas(0.01, 0.02, 1e-3))  # 2 m off: a device glitch
    poses = graph.optimize(update=False).poses
    assert np.linalg.norm(poses[6][:3, 3] - truth[6][:3, 3]) < 0.1  # the chain holds against it
    copy = _graph(robust="cauchy", robust_k=1.0)
    copy.load_state_dict(unpack(pack(graph.state_dict())))
    assert [p.key for p in copy.priors] == [6]
    np.testing.assert_allclose(copy.optimize(update=False).poses[6], poses[6], atol=1e-6)
